"""The scene representation (paper Sec. 3.1): multi-scale axis-aligned feature planes, the shallow decoders, and
the field that combines them into a truncated SDF and a colour."""
