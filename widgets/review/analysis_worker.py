"""The reviewer's analysis off the GUI thread: the flat field's physics (a finite-element solve the first time a
session is analysed), the depth model and :meth:`SessionAnalysis.run`, in a worker thread.

The worker touches no Qt object: the window hands it requests and reads their progress and results on its own
timer, so a window closed or deleted while an analysis runs leaves nothing the worker could reach. Requests are
served newest first: a request that has not started when a newer one comes is dropped, and the one running is
told it is superseded and, if the newer one does not need the physics it is building, cancelled. A cancelled
build stops at its next progress report; a superseded analysis stops at its next one (each record of the flat
field's pattern, each tumour the depth model takes in turn, each of its finite-element solves: a couple of
seconds apart at most), what the depth model has solved kept for the next request. What cannot be interrupted
(a factory that reports no progress) runs to its end; its result then carries an old generation, and the window
drops it.

The thread exists only while there are requests: it ends when none is left, so a closed window leaves no
thread behind once the step it was in is over. Nothing joins it: the interpreter waits for it at exit (it is
not a daemon, which could die half-way through writing the tissue model's cache), for that step alone.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from session.analysis import AnalysisParams, DepthModel, SessionAnalysis
from session.flatfield import FlatFieldError, Reference
from session.physics import HomogeneousTissue
from session.reader import Session
from session.stitch import StitchError
from tissue.mechanics.progress import Progress

PhysicsFactory = Callable[[Session, Progress], HomogeneousTissue | None]
THREAD_NAME = "review-analysis"


class Cancelled(Exception):
    """A physics build or an analysis stopped because no request needs it any more."""


class SessionModels:
    """What every analysis of one session shares, made at most once: the physics per option (label) and the
    depth model, each with the reason it could not be had. Used by the worker thread alone."""

    def __init__(self, session: Session, physics: Mapping[str, PhysicsFactory],
                 depth_model: Callable[[Session], DepthModel] | None):
        self.session = session
        self._factories = dict(physics)
        self._depth_factory = depth_model
        self._physics: dict[str, tuple[HomogeneousTissue | None, str]] = {}
        self._depth: tuple[DepthModel | None, str] | None = None

    def has_physics(self, label: str) -> bool:
        return label in self._physics

    def physics(self, label: str, progress: Progress) -> tuple[HomogeneousTissue | None, str]:
        if label not in self._physics:
            try:
                self._physics[label] = (self._factories[label](self.session, progress), "")
            except ValueError as err:
                self._physics[label] = (None, f"Flat-field physics {label!r} unavailable: {err}; analysed without it.")
        return self._physics[label]

    def depth_model(self) -> tuple[DepthModel | None, str]:
        if self._depth_factory is None:
            return None, ""
        if self._depth is None:
            try:
                self._depth = (self._depth_factory(self.session), "")
            except ValueError as err:
                self._depth = (None, f"Model-based depth unavailable: {err}.")
        return self._depth


@dataclass
class Outcome:
    """A request's end: the analysis and what it had to do without (in words), or the parameter the session
    cannot be analysed with, or an unexpected failure."""

    analysis: SessionAnalysis | None = None
    problems: list[str] = field(default_factory=list)
    not_applied: str = ""
    error: BaseException | None = None


class AnalysisRequest:
    """One analysis asked for: which session (its shared models), the physics option (None: none), the
    parameters and the reference. The worker writes :attr:`progress` and :attr:`outcome`; the window reads them."""

    def __init__(self, generation: int, models: SessionModels, physics_label: str | None, params: AnalysisParams,
                 reference: Reference | None):
        self.generation = generation
        self.models = models
        self.physics_label = physics_label
        self.params = params
        self.reference = reference
        self.progress: tuple[str, float | None] = ("waiting for the previous analysis", None)
        self.outcome: Outcome | None = None  # None after it ends: it was superseded or cancelled
        self.superseded = threading.Event()
        self.cancelled = threading.Event()

    def needs_build_of(self, other: AnalysisRequest) -> bool:
        """Whether this request will use the physics ``other`` may be building."""
        return self.models is other.models and self.physics_label == other.physics_label

    def run(self) -> None:
        """Every step, in the worker thread; never raises (a failure is the outcome's)."""
        try:
            self.outcome = self._analyse()
        except Cancelled:
            self.outcome = None
        except Exception as err:  # handed to the GUI thread, which raises it there: no failure goes unseen
            self.outcome = Outcome(error=err)

    def _analyse(self) -> Outcome | None:
        models, problems = self.models, []
        physics = None
        if self.physics_label is not None:
            label = self.physics_label
            # short: the status bar holds it beside the file's name, and the physics combo names the option
            step = "the flat field" if models.has_physics(label) else "the flat field's tissue model"
            self.progress = (step, None)

            def report(fraction: float, message: str) -> None:
                if self.cancelled.is_set():
                    raise Cancelled
                self.progress = (f"{step}: {message}", fraction)

            physics, problem = models.physics(label, report)
            problems.append(problem)
        if self.superseded.is_set():
            return None
        self.progress = ("the depth model", None)
        depth_model, problem = models.depth_model()
        problems.append(problem)
        if self.superseded.is_set():
            return None
        self.progress = ("tumours and maps", None)
        session = models.session

        def analysing(fraction: float, message: str) -> None:
            if self.superseded.is_set():  # its result would be dropped
                raise Cancelled
            self.progress = (message, fraction)

        try:
            try:
                analysis = SessionAnalysis.run(session, self.params, physics, self.reference, depth_model, analysing)
            except FlatFieldError as err:
                problems.append(f"Reference palpation not used: {err}.")
                analysis = SessionAnalysis.run(session, self.params, physics, None, depth_model, analysing)
        except StitchError as err:  # the cell size is too fine for this session's extent
            return Outcome(not_applied=str(err))
        return Outcome(analysis, [p for p in problems if p])


class AnalysisWorker:
    """Serves requests one at a time on a thread of its own, newest first (see the module's docstring)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._pending: AnalysisRequest | None = None
        self._running: AnalysisRequest | None = None
        self._finished: list[AnalysisRequest] = []
        self._thread: threading.Thread | None = None

    def submit(self, request: AnalysisRequest) -> None:
        with self._lock:
            self._pending = request  # one that had not started is dropped unseen
            running = self._running
            if running is not None:
                running.superseded.set()
                if not request.needs_build_of(running):
                    running.cancelled.set()
            if self._thread is None:
                self._thread = threading.Thread(target=self._serve, name=THREAD_NAME)
                self._thread.start()

    def cancel(self) -> None:
        """Drop what waits and stop what runs as soon as it can; returns at once."""
        with self._lock:
            self._pending = None
            if self._running is not None:
                self._running.superseded.set()
                self._running.cancelled.set()

    def take_finished(self) -> list[AnalysisRequest]:
        """The requests that ended since the last call, oldest first."""
        with self._lock:
            done, self._finished = self._finished, []
        return done

    def running(self) -> AnalysisRequest | None:
        with self._lock:
            return self._running

    def alive(self) -> bool:
        with self._lock:
            return self._thread is not None

    def _serve(self) -> None:
        while True:
            with self._lock:
                request = self._running = self._pending
                self._pending = None
                if request is None:
                    self._thread = None
                    return
            request.run()
            with self._lock:
                self._running = None
                self._finished.append(request)
