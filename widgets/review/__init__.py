"""The session reviewer: :class:`ReviewWindow` and the pieces it is built from."""

from widgets.review.map_view import GridMapView
from widgets.review.recent import RecentSessions
from widgets.review.timeline import TimelineWidget
from widgets.review.window import ReviewWindow

__all__ = ["GridMapView", "RecentSessions", "ReviewWindow", "TimelineWidget"]
