"""interreal.allocator: freed image-sized blocks are reused instead of mapped afresh (page faults counted)."""

import subprocess
import sys

import pytest

CHURN = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from interreal.allocator import keep_freed_blocks
    assert keep_freed_blocks()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    b = np.ones(40 << 20, np.uint8)  # 40 MB: over glibc's largest own threshold (32 MB), mapped afresh by default
    del b
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", CHURN, mode], capture_output=True, text=True, check=True)
    return int(out.stdout.strip())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_blocks_are_reused_not_faulted_in_again():
    default, kept = faults("default"), faults("keep")
    # 20 blocks faulted in by default (10 k pages each, fewer with transparent huge pages); kept: the first only
    assert default > 2000, default
    assert kept < 0.2 * default, (default, kept)


def test_the_users_own_threshold_wins(monkeypatch):
    from interreal.allocator import keep_freed_blocks
    monkeypatch.setenv("MALLOC_MMAP_THRESHOLD_", "131072")
    assert keep_freed_blocks() is False
