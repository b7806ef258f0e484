"""A cold-start run's plan, one pose at a time: explore a little, estimate, then grow bolder.

The state machine behind a run that knows only the board, the setup, the safety box and that
the camera sees the board at the start (issue 17):

1. **Explore.** Small tool rotations about the tool's own axes (``EXPLORE_ROT_DEG``) from the
   start pose. A move that loses the board is not repeated: the next one leaves from the last
   good pose and turns the other way by half as much. Each move is checked against the box.
2. **Bootstrap.** From three good views on, ``calib.coldstart.bootstrap`` estimates the focal
   length, the hand-eye and the board pose; the estimate is accepted once its chain reprojects
   within ``ACCEPT_RMS_PX``, otherwise exploration goes on (at most ``MAX_EXPLORE`` moves).
   Guesses are priors there: a wrong one is found out and reported in :attr:`ColdStart.notes`.
3. **Plan by what a view teaches.** Each next station is ``calib.viewselect.choose_view``'s
   pick under the latest estimate, refitted (``calib.coldstart.refit``) after every good view.
   The reach (tilt, distance band, roll, step) grows with the number of good views and shrinks
   by half after a view where the board was lost (recorded with its reason, and avoided
   afterwards); the step is measured from the last good pose, so the robot backs off towards
   it instead of wandering. When no candidate is feasible even at a small reach, the plan ends
   (``no_feasible_view``).

The class does no I/O: a caller moves the robot to :meth:`ColdStart.propose`'s pose, detects
the board and hands the outcome to :meth:`ColdStart.record` (the service's capture thread, the
benchmark's simulated cell).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from calib.boards import Board
from calib.chain import camera_from_robot
from calib.coldstart import GOOD_FIT_PX, Bootstrap, Guess, View, bootstrap, refit
from calib.geometry import make_transform
from calib.so3 import exp as so3_exp
from calib.viewselect import (
    CAMERA_MARGIN_M,
    Choice,
    History,
    Reach,
    Scene,
    choose_view,
    image_margin,
    start_roll,
)

#: Exploration: tool rotation per move, and the most exploratory moves before planning.
EXPLORE_ROT_DEG = 5.0
MAX_EXPLORE = 8
#: The bootstrap is trusted once the chain reprojects within this RMS (px).
ACCEPT_RMS_PX = GOOD_FIT_PX
#: Smallest reach scale tried before the plan declares no feasible view.
MIN_SCALE = 0.2
#: Exploration axes in the tool frame, in order (x, y, then the opposite ways, then z).
_AXES = ((0, 1.0), (1, 1.0), (0, -1.0), (1, -1.0), (2, 1.0), (2, -1.0))


@dataclass(frozen=True)
class Proposal:
    """Where to go next: ``T_base_tcp`` (4, 4) to command, ``kind`` ``explore`` or
    ``station``, the ``predicted`` hand-eye σ (rad, m) with it (stations), and the planning
    ``compute_s`` (CPU seconds) it took."""

    T_base_tcp: np.ndarray
    kind: str
    predicted: tuple[float, float] | None = None
    compute_s: float = 0.0


@dataclass
class _Log:
    """What happened so far: good views, commanded poses that lost the board and why."""

    views: list[View] = field(default_factory=list)
    failed: list[np.ndarray] = field(default_factory=list)
    reasons: list[str] = field(default_factory=list)
    explore_moves: int = 0


class ColdStart:
    """The plan of one cold-start run (module docstring).

    Parameters
    ----------
    scene : the board, setup, image size, safety box and tolerance (``calib.viewselect``).
    start : T_base_tcp (4, 4) where the robot was jogged to (the camera sees the board).
    guess : optional priors (``calib.coldstart.Guess``).
    seed : seed of the candidate draws (a run is reproducible).
    """

    def __init__(self, scene: Scene, start: np.ndarray, *, guess: Guess | None = None,
                 seed: int = 0) -> None:
        self.scene = scene
        self.start = np.asarray(start, dtype=float)
        self.guess = guess
        self.rng = np.random.default_rng(seed)
        self.log = _Log()
        self.estimate: Bootstrap | None = None
        self.notes: list[str] = []
        self.scale = 1.0
        self._axis = 0
        self._pending: tuple[int, float, float] | None = None
        self._retry: tuple[int, float, float] | None = None
        self._exploring = True  # the pose proposed last was exploratory
        self._last_good = self.start
        self._d0 = 0.0

    @property
    def board(self) -> Board:
        return self.scene.board

    # ---- the caller's two calls -------------------------------------------------------------

    def propose(self) -> Proposal | None:
        """The next pose to visit, or None when no feasible view remains."""
        t0 = time.process_time()
        if not self.log.views and not self.log.failed:
            return Proposal(self.start, "explore")
        self._exploring = self.estimate is None
        if self.estimate is None:
            P = self._next_exploration()
            if P is not None:
                return Proposal(P, "explore", compute_s=time.process_time() - t0)
            if not self._accept_best_effort():
                return None
        choice = self._next_station()
        if choice is None:  # the estimate allows no view: explore on while moves are left
            self._exploring = True
            P = self._next_exploration()
            return None if P is None else Proposal(P, "explore",
                                                   compute_s=time.process_time() - t0)
        return Proposal(choice.T_base_tcp, "station", choice.predicted,
                        time.process_time() - t0)

    def record(self, commanded: np.ndarray, view: View | None, reason: str | None = None
               ) -> None:
        """The outcome at ``commanded`` (4, 4): the good ``view`` or why there was none."""
        if self._exploring and (self.log.views or self.log.failed):
            self.log.explore_moves += 1
        if view is None:
            if self._exploring and self._pending is not None and self._pending[2] == 1.0:
                axis, sign, _ = self._pending
                self._retry = (axis, -sign, 0.5)
            self.log.failed.append(np.asarray(commanded, dtype=float))
            self.log.reasons.append(reason or "board not detected")
            self.scale = max(MIN_SCALE, 0.5 * self.scale)
            return
        self.log.views.append(view)
        self._last_good = view.T_base_tcp
        self.scale = min(1.0, 1.5 * self.scale)
        if self.estimate is None:
            self._try_bootstrap(final=False)
        else:
            try:
                self.estimate = refit(self.log.views, self.board, self.scene.setup,
                                      self.estimate)
            except ValueError as exc:
                self.notes.append(f"refit after {len(self.log.views)} views failed ({exc}); "
                                  "keeping the previous estimate")

    # ---- exploration and bootstrap ----------------------------------------------------------

    def _next_exploration(self) -> np.ndarray | None:
        """The next small exploratory move from the last good pose, None when exhausted.

        After a lost board the same axis is tried the other way by half as much; moves whose
        tcp would leave the box are skipped."""
        lo, hi = self.scene.box
        while self.log.explore_moves < MAX_EXPLORE:
            if self._retry is not None:
                (axis, sign, size), self._retry = self._retry, None
            elif self._axis < len(_AXES):
                (axis, sign), size = _AXES[self._axis], 1.0
                self._axis += 1
            else:
                return None
            self._pending = (axis, sign, size)
            rotvec = np.zeros(3)
            rotvec[axis] = sign * size * np.deg2rad(EXPLORE_ROT_DEG)
            P = self._last_good @ make_transform(so3_exp(rotvec), np.zeros(3))
            if (P[:3, 3] >= lo + 0.01).all() and (P[:3, 3] <= hi - 0.01).all():
                return P
        return None

    def _try_bootstrap(self, *, final: bool) -> None:
        """Estimate the cell from the views so far; keep it if it fits (or ``final``)."""
        if len(self.log.views) < 3:
            return
        try:
            est = bootstrap(self.log.views, self.board, self.scene.image_size,
                            self.scene.setup, self.guess)
        except ValueError:
            return
        if not final and (est.rms_px > ACCEPT_RMS_PX or not self._camera_plausible(est)):
            return
        if est.rejected_guess:
            self.notes.append(est.rejected_guess)
        self.estimate = est
        C0 = _view(self.start, est, self.scene.setup)
        self._d0 = float(np.linalg.norm(C0[:3, 3]))
        self.scene = replace(self.scene, start_roll=start_roll(C0))

    def _camera_plausible(self, est: Bootstrap) -> bool:
        """Whether the estimate puts the camera at the start inside the box, where the user
        jogged it (eye-in-hand; a fixed camera may be anywhere)."""
        if self.scene.setup != "eye_in_hand":
            return True
        p = (self.start @ est.cell.hand_eye)[:3, 3]
        lo, hi = self.scene.box
        return bool((p >= lo).all() and (p <= hi).all())

    def _accept_best_effort(self) -> bool:
        """After the last exploratory move: take the bootstrap as it is, if there is one."""
        self._try_bootstrap(final=True)
        return self.estimate is not None

    # ---- planned stations -------------------------------------------------------------------

    def reach(self) -> Reach:
        """How bold the next station may be: the region of views grows with the good views;
        the step from the last good pose also scales with ``scale`` (halved after a lost
        board or when no view was feasible, grown again after good views)."""
        k = len(self.log.views)
        s = self.scale
        band = (1.0 - min(0.35, 0.05 + 0.03 * k), 1.0 + min(0.5, 0.05 + 0.04 * k))
        return Reach(max_tilt_deg=min(50.0, 10.0 + 4.0 * k),
                     band=(self._d0 * band[0], self._d0 * band[1]),
                     max_roll_deg=min(90.0, 15.0 + 8.0 * k),
                     step=(np.deg2rad(s * min(180.0, 10.0 + 8.0 * k)),
                           s * min(0.4, 0.05 + 0.03 * k)),
                     margin_frac=max(0.03, 0.15 - 0.01 * k),
                     camera_margin=self._camera_margin())

    def _relaxed(self, reach: Reach) -> Reach:
        """``reach`` asking no more image border than most of what the last good view left:
        a board jogged near the image edge must not rule out every view near it."""
        assert self.estimate is not None
        last = _view(self._last_good, self.estimate, self.scene.setup)
        now = float(image_margin(last[None], self.estimate.cell, self.scene)[0])
        return replace(reach, margin_frac=min(reach.margin_frac, max(0.005, 0.8 * now)))

    def _camera_margin(self) -> float:
        """The camera's margin inside the box: a base margin plus three times the estimate's
        hand-eye translation σ (its position in the base frame is only as good as that)."""
        assert self.estimate is not None
        sd = np.sqrt(np.clip(np.diag(self.estimate.covariance)[14:17], 0.0, None))
        return float(CAMERA_MARGIN_M + 3.0 * np.linalg.norm(sd))

    def _next_station(self) -> Choice | None:
        """The most informative feasible view, shrinking the reach until one is found."""
        assert self.estimate is not None
        history = History(visited=np.stack([v.T_base_tcp for v in self.log.views]),
                          last_good=self._last_good,
                          failed=np.array(self.log.failed).reshape(-1, 4, 4))
        while True:
            reach = self.reach()
            choice = choose_view(self.estimate.cell, self.scene, reach, history, self.rng)
            if choice is None:
                choice = choose_view(self.estimate.cell, self.scene, self._relaxed(reach),
                                     history, self.rng)
            if choice is not None or self.scale <= MIN_SCALE:
                return choice
            self.scale = max(MIN_SCALE, 0.5 * self.scale)


def _view(T_base_tcp: np.ndarray, est: Bootstrap, setup: str) -> np.ndarray:
    """T_cam_target (4, 4) of a tcp pose under the estimate."""
    return camera_from_robot(T_base_tcp, est.cell.hand_eye, est.cell.target_pose, setup)
