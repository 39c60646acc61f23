"""Opens a file the way the console does, in a process of its own, for tests/session/test_hostile_files.py: a
file that makes a reader wait forever or eat memory then fails its test (the parent's time-out, a MemoryError
under the address-space cap set here) instead of stalling or starving the test run.

    python -m tests.session.open_child session PATH      open_session(PATH)
    python -m tests.session.open_child swapped PATH      the same, with a FIFO put at PATH once it was checked
    python -m tests.session.open_child reference PATH    Reference.load(PATH, (4, 15))

A refusal prints its message and exits 0; a file that opens prints "opened" and exits 3. Either way the last
line is the process's peak resident memory in MiB (VmHWM: getrusage's ru_maxrss would count the memory of
the parent it was forked from too).
"""

from __future__ import annotations

import os
import resource
import sys
from pathlib import Path

from session import reader
from session.flatfield import FlatFieldError, Reference
from session.reader import SessionFileError, open_session

# What opening a file may add to this process's address space: a reader that tries to load a crafted
# claim of gigabytes fails at once with a MemoryError, however much memory the machine has.
ADDRESS_SPACE_BUDGET_BYTES = 1 << 30


def _status_kib(key: str) -> int:
    status = Path("/proc/self/status").read_text()
    return int(next(line for line in status.splitlines() if line.startswith(f"{key}:")).split()[1])


def _cap_address_space() -> None:
    limit = _status_kib("VmSize") * 1024 + ADDRESS_SPACE_BUDGET_BYTES
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def _swap_in_a_fifo_after_the_check() -> None:
    """Put a FIFO at the path once it has been checked, before HDF5 opens it: the race a reader that checks
    the path and then opens it by name would lose (and wait on the FIFO for ever)."""
    check = reader._open_regular_file

    def check_then_swap(path: Path):
        checked = check(path)
        path.rename(path.with_name(path.name + ".moved"))
        os.mkfifo(path)
        return checked

    reader._open_regular_file = check_then_swap


def main(kind: str, path: str) -> int:
    _cap_address_space()
    if kind == "swapped":
        _swap_in_a_fifo_after_the_check()
    try:
        if kind == "reference":
            Reference.load(path, (4, 15))
        else:
            open_session(path).close()
        print("opened")
        code = 3
    except (SessionFileError, FlatFieldError) as err:
        print(err)
        code = 0
    print(_status_kib("VmHWM") // 1024)
    return code


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
