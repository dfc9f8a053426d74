"""Tracking (paper Sec. 3.4): the front end that predicts, tracks and decides keyframes, and the two trackers
(rendering, as in the paper; Gauss-Newton on the SDF, for live use on a CPU)."""
