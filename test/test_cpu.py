"""CPU settings: denormals flushed in every torch thread inside the block and restored after it; glibc keeps freed
memory; a worker's start-up objects out of the garbage collector's reach."""
import gc
import platform

import pytest
import torch

from eslam_core.cpu import FullCollections, denormals_flushed, flat_nonzero, freeze_start_up_objects, keep_freed_memory
from eslam_core.native import load_kernel


def nonzero_after_arithmetic(x: torch.Tensor) -> int:
    return int(torch.count_nonzero(x * 1.0))


def test_denormals_are_flushed_in_all_torch_threads_inside_the_block_only():
    if load_kernel("denormals") is None:
        pytest.skip("no C compiler")
    # The largest float32 denormal (just below 1.18e-38), set bitwise; big enough for torch to run it threaded.
    tiny = torch.full((1 << 22,), 0x007FFFFF, dtype=torch.int32).view(torch.float32)
    assert nonzero_after_arithmetic(tiny) == len(tiny)
    with denormals_flushed():
        with denormals_flushed():  # nested blocks: only the outermost switches back
            pass
        assert nonzero_after_arithmetic(tiny) == 0  # read as zero by every thread's arithmetic
    assert nonzero_after_arithmetic(tiny) == len(tiny)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_glibc_keeps_freed_memory():
    assert keep_freed_memory()


@pytest.mark.parametrize("dtype", [torch.bool, torch.uint8])
@pytest.mark.parametrize("share", [0.0, 0.3, 1.0])
def test_flat_nonzero_equals_torch_nonzero(dtype, share):
    mask = (torch.rand(480, 640) < share).to(dtype)
    got = flat_nonzero(mask)
    assert got.dtype == torch.int64
    torch.testing.assert_close(got, torch.nonzero(mask.reshape(-1)).squeeze(1))


def test_start_up_objects_are_frozen_and_full_collections_counted():
    start_up = [[i] for i in range(10_000)]  # objects that live as long as the process (a worker's modules)
    try:
        freeze_start_up_objects()
        collections = FullCollections()
        assert gc.get_freeze_count() >= len(start_up)
        walked = gc.get_objects(generation=2)  # what a full collection walks
        assert not any(o is start_up or o is start_up[0] for o in walked)
        del walked
        gc.collect(1)  # (a younger generation's collection: not a full one)
        assert collections.count == 0
        gc.collect()
        assert collections.count == 1 and collections.seconds > 0
        collections.close()
        gc.collect()
        assert collections.count == 1
    finally:
        gc.unfreeze()
