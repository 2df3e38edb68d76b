"""The host side of the product's process (``affinebody._host``): the C heap that
``keep_freed_memory`` tunes for the command line and the workers."""

from __future__ import annotations

import subprocess
import sys

import pytest

# 16 arrays of 2 MiB allocated, touched and freed, four times over: the page faults of each round
REFILL = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from affinebody import _host
    assert _host.keep_freed_memory()
faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(4):
    start = faults()
    arrays = [np.ones(2**18) for _ in range(16)]
    del arrays
    print(faults() - start)
"""


def refill_faults(mode: str) -> list[int]:
    out = subprocess.run([sys.executable, "-c", REFILL, mode], capture_output=True, text=True,
                         check=True, timeout=120)
    return [int(line) for line in out.stdout.split()]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt (Linux)")
def test_freed_memory_is_refilled_without_page_faults():
    """32 MiB freed and allocated again: with glibc's defaults the heap gives the pages back
    and every round faults them in afresh (8192 pages of 4 KiB); after keep_freed_memory the
    rounds after the first reuse the mapped pages (no fault per MiB)."""
    default, kept = refill_faults("default"), refill_faults("keep")
    pages = 16 * 2 * 2**20 // 4096
    assert min(default[1:]) > pages // 2, default  # the pattern does fault by default
    assert kept[0] > pages // 2, kept  # the first round maps the pages
    assert max(kept[1:]) < pages // 100, kept  # later rounds reuse them
