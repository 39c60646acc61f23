"""The list of recently opened session files, kept in QSettings and shared by the reviewer and the console."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from PySide6 import QtCore, QtWidgets

KEY = "review/recent_sessions"


class RecentSessions:
    """Most recent first, at most ``limit`` entries, without duplicates; files that vanished are skipped."""

    def __init__(self, settings: QtCore.QSettings | None = None, limit: int = 10):
        if limit < 1:
            raise ValueError(f"limit must be >= 1, got {limit!r}")
        self._settings = settings if settings is not None else QtCore.QSettings("palpation-console", "review")
        self.limit = limit

    def paths(self) -> list[Path]:
        raw = self._settings.value(KEY, [])
        if isinstance(raw, str):  # QSettings gives a lone entry back as a plain string
            raw = [raw]
        return [Path(p) for p in (raw or []) if p and Path(p).is_file()]

    def add(self, path: str | Path) -> None:
        path = Path(path).resolve()
        entries = [path] + [p for p in self.paths() if p.resolve() != path]
        self._settings.setValue(KEY, [str(p) for p in entries[: self.limit]])
        self._settings.sync()

    def clear(self) -> None:
        self._settings.remove(KEY)
        self._settings.sync()

    def fill_menu(self, menu: QtWidgets.QMenu, open_path: Callable[[Path], None]) -> None:
        """Replace ``menu``'s entries with the recent files (call it from ``menu.aboutToShow``)."""
        menu.clear()
        paths = self.paths()
        for i, path in enumerate(paths, 1):
            action = menu.addAction(f"&{i % 10}  {path.name}")
            action.setToolTip(str(path))
            action.setData(str(path))
            action.triggered.connect(lambda _=False, p=path: open_path(p))
        if not paths:
            menu.addAction("No recent sessions").setEnabled(False)
        else:
            menu.addSeparator()
            menu.addAction("Clear the list", self.clear)
