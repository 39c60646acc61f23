"""Whether Qt can open a window here: told in one line before a command builds anything, not after, by Qt's
abort (exit 134 and a paragraph about plugins)."""

from __future__ import annotations

import os
import sys


def display_problem(environ=os.environ, command: str = "run", find_library=None) -> str:
    """Why Qt could not open a window here, or '' (told before the tissue model is built or a session read,
    not after, by Qt's abort: exit 134 and a paragraph about plugins)."""
    if environ.get("QT_QPA_PLATFORM"):  # a platform was chosen (offscreen, vnc, ...): Qt says if it fails
        return ""
    if not sys.platform.startswith("linux"):
        return ""
    if not (environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY")):
        return ("no display to open the console on (neither DISPLAY nor WAYLAND_DISPLAY is set): run it under a "
                f"virtual one (xvfb-run -a palpation-console {command}), or set QT_QPA_PLATFORM=offscreen for a "
                "headless check")
    if not environ.get("WAYLAND_DISPLAY"):
        import ctypes.util

        # Qt 6's X11 platform will not load without it, and pip cannot install it
        if (find_library or ctypes.util.find_library)("xcb-cursor") is None:
            return ("Qt's X11 platform needs the system library libxcb-cursor0, which is not installed: "
                    "sudo apt-get install libxcb-cursor0 (or run make bootstrap-run)")
    return ""
