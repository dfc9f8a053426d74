"""Shared fixtures: small synthetic RGB-D sequences of the embedded room, generated once per test session."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from eslam_core.datasets import open_dataset
from eslam_core.datasets.synthetic import generate_scene


@pytest.fixture(scope="session")
def room_sequence(tmp_path_factory):
    """30 frames of the synthetic room at 160x120 with realistic sensor noise and holes."""
    path = generate_scene(tmp_path_factory.mktemp("room") / "seq", n_frames=30, width=160, height=120, seed=3)
    return open_dataset(path, "tum")


@pytest.fixture(scope="session")
def long_room(tmp_path_factory):
    """The camera walks 3.7 m along a room twice as long as the embedded one, looking across it (150 frames at
    160x120): long enough for several 1 m submaps."""
    path = generate_scene(tmp_path_factory.mktemp("long") / "seq", n_frames=150, width=160, height=120, seed=1,
                          layout="long_room")
    return open_dataset(path, "tum")


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)
