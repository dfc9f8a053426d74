"""Rendering and its objective (paper Sec. 3.2-3.3): depth samples along rays, SDF-based volume rendering, the
losses; and mesh ray casting for synthetic data and evaluation."""
