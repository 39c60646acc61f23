"""Suite-wide guards: headless Qt, sandboxed settings and caches, nothing left running after a test."""

import multiprocessing
import os
import threading
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

TEST_CACHE = Path(__file__).resolve().parents[1] / "build" / "test-cache"


@pytest.fixture(autouse=True)
def _sandbox(tmp_path_factory, monkeypatch):
    base = tmp_path_factory.mktemp("sandbox")
    # tissue models are precomputed once per machine (seconds per phantom) and shared by every test run
    monkeypatch.setenv("PALPATION_CACHE_DIR", str(TEST_CACHE))
    monkeypatch.setenv("PALPATION_DATA_DIR", str(base / "data"))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(base / "config"))
    yield


@pytest.fixture(autouse=True)
def _nothing_left_running():
    threads_before = {t.ident for t in threading.enumerate()}
    yield
    children = multiprocessing.active_children()
    for child in children:
        child.kill()
        child.join(5)
    assert not children, f"test left processes running: {children}"
    leftover = [t for t in threading.enumerate() if t.ident not in threads_before and t.is_alive()
                and not t.daemon]
    assert not leftover, f"test left threads running: {leftover}"
