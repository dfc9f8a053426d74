"""ESLAM: efficient dense RGB-D SLAM with multi-scale axis-aligned feature planes (Johari et al., CVPR 2023)."""

__version__ = "0.1.0"
