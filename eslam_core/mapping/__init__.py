"""Mapping (paper Sec. 3.4): the scene map (extent, field, keyframe store, observed space) and its mapping step."""
