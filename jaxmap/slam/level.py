"""Levelling a pose by the scene's vertical structure (facades, walls, poles): a gravity reference
from the scan itself.

Why: scan matching fixes each frame's rotation relative to the map it is tracked against, so a tilt
picked up early (a young map, an odometry that tilts on a sparse sensor) is carried along, and the
height error it makes grows with the distance driven (0.05-0.08 deg on the suite's streets: 2-3 cm
low on the far side of a 40 m block). A rigid tilt closes every loop, so no loop closure sees it.
Vertical surfaces are vertical in every frame: their normals, rotated into the world, must be
perpendicular to the world's up. A scan's levelling rotation (`level_rotation`) measures its tilt
against that: 6 mdeg from the true tilt on average (at most ~20) on the suite's clean streets, ~80
with 2 cm range noise (at the true poses). The up itself is the first frame's facades' (its pose is given), averaged
with the next frames' while one frame is too noisy to say it (`Leveller`).

Shapes: normals [M, 3] float (sensor frame, unit), rotations [3, 3] world <- sensor, vectors [3] world.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxmap.geometry import rotation_from_axis_angle

FIRST_BAND_DEG = 10.0            # the first pass: normals within this of horizontal (edges, corners and
                                 # foliage give normals off the band)
PASSES = 4                       # each later pass narrows the band to BAND_SIGMAS spreads of the last one's
BAND_SIGMAS = 3.0                # residuals (robust: 1.4826 MAD), at least MIN_BAND_DEG: 0.5 deg on the clean
MIN_BAND_DEG = 0.5               # streets (a fixed 1 deg band left 2-3x their frame-0 error), ~2 deg at 2 cm noise
MEASURED = 0.2                   # an axis with less than this share of the best axis's facade weight is not
                                 # measured (held at 0)
MIN_NORMALS = 200                # fewer near-vertical normals than this: no measurement (a field, a tunnel)
REFERENCE_STDERR_DEG = 0.005     # the up direction averages frames until its standard error is below this


class Level(NamedTuple):
    """A scan's tilt against an up direction: `rotvec` [3] world rotation (perpendicular to up) that
    makes its near-vertical normals horizontal (apply as exp(rotvec) @ R); `count` the normals used in
    the last pass (0: no measurement, rotvec 0); `stderr` its standard error (radians, the least
    measured axis; inf when nothing was measured) from the residuals' spread."""
    rotvec: np.ndarray
    count: int
    stderr: float = float("inf")


def rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """[3] rotation vector (axis times angle, radians) -> [3, 3] float64 rotation."""
    w = np.asarray(w, np.float64)
    a = float(np.linalg.norm(w))
    return np.eye(3) if a < 1e-15 else np.asarray(rotation_from_axis_angle(w, a), np.float64)


def level_rotation(normals_s: np.ndarray, R: np.ndarray, up: np.ndarray, passes: int = PASSES,
                   min_normals: int = MIN_NORMALS) -> Level:
    """The world rotation exp(w) (w perpendicular to `up`) that makes the scan's near-vertical surfaces
    vertical: least squares of (up . exp(w) R n)^2 over the normals n within a band around horizontal,
    linearised and solved again `passes` times, each band fitted to the last pass's residuals. The
    rotation about `up` changes nothing and is held at 0; a scan with one facade direction fixes only
    the tilt across it (the other axis is held at 0). Returns `Level`."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    n_w = np.asarray(normals_s, np.float64) @ np.asarray(R, np.float64).T
    w, band_deg = np.zeros(3), FIRST_BAND_DEG
    for _ in range(passes):
        n = n_w @ rotvec_matrix(w).T
        c = n @ up
        band = np.abs(c) < np.sin(np.radians(band_deg))
        count = int(band.sum())
        if count < min_normals:
            return Level(np.zeros(3), 0)
        a = np.cross(n[band], up)
        # up . (n + w x n) = c + w . (n x up): minimise sum (c + a . w)^2 over w, solved only along the
        # axes the facades measure (eigenvalues >= MEASURED of the largest): along a straight street's
        # one facade direction the other axis is seen by clutter alone, which would invent a tilt there
        lam, vec = np.linalg.eigh(a.T @ a)
        keep = lam >= MEASURED * lam[-1]
        dw = vec[:, keep] @ ((vec[:, keep].T @ -(a * c[band, None]).sum(0)) / lam[keep])
        w = w + dw
        res = c[band] + a @ dw
        sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))
        band_deg = min(FIRST_BAND_DEG, max(MIN_BAND_DEG, BAND_SIGMAS * np.degrees(sigma)))
    return Level(w - up * (w @ up), count, sigma / float(np.sqrt(lam[keep].min())))


def facade_up(normals_s: np.ndarray, R: np.ndarray, up_guess: np.ndarray) -> tuple[np.ndarray, float] | None:
    """([3] the up direction (world) that the scan's near-vertical surfaces say, starting from
    `up_guess` (within a few degrees), its standard error (radians)); None when too few are seen."""
    lv = level_rotation(normals_s, R, up_guess)
    if lv.count == 0:
        return None
    # exp(w) R n is perpendicular to up_guess  <=>  R n is perpendicular to exp(-w) up_guess
    return rotvec_matrix(-lv.rotvec) @ (np.asarray(up_guess, np.float64) / np.linalg.norm(up_guess)), lv.stderr


class Leveller:
    """The front end's levelling state: the world's up, and the fraction `gain` of each frame's tilt
    against it that is turned away.

    The up is the first frame's facades' (its pose is the one given: the others carry the odometry's
    tilt, up to 0.18 deg two frames in on the VLP-32C street, which an average over ten frames took
    into the reference), weighted with the next frames' (at most `reference_frames` in all) only while
    its standard error is above REFERENCE_STDERR_DEG: with 2 cm range noise one frame says the up to
    50-113 mdeg (the noisy street's first frames), and the reference takes ten."""

    def __init__(self, gain: float, reference_frames: int, first_pose: np.ndarray, up_sensor=(0.0, 0.0, 1.0)):
        self.gain, self.reference_frames = float(gain), int(reference_frames)
        self.guess = np.asarray(first_pose, np.float64)[:3, :3] @ np.asarray(up_sensor, np.float64)
        self.up_sum = np.zeros(3)        # the reference frames' ups, each weighted by 1 / stderr^2
        self.weight = 0.0                # their summed weight (1 / the reference's stderr^2)
        self.frames = 0                  # frames seen while the reference was open
        self.stderr: list[float] = []    # per frame: its tilt's standard error (radians; the first frame's
                                         # pose is the given one: 0; inf: not measured)

    @property
    def up(self) -> np.ndarray:
        """[3] the world's up (the guess, the first pose's sensor z, before any facade is seen)."""
        s = np.linalg.norm(self.up_sum)
        return self.up_sum / s if s > 0 else self.guess

    @property
    def reference_open(self) -> bool:
        """The up still takes frames in: fewer than `reference_frames` seen, and not yet precise."""
        precise = self.weight > 0 and 1.0 / np.sqrt(self.weight) < np.radians(REFERENCE_STDERR_DEG)
        return self.frames < self.reference_frames and not precise

    def __call__(self, pose: np.ndarray, normals_s: np.ndarray, turn: bool = True) -> np.ndarray:
        """[4, 4] the pose turned about its own position by `gain` times its scan's tilt against `up` (the
        pose as given when the scan measures nothing, or `turn` is False: the first frame's given pose).
        While the reference is open the frame's up joins it first (measured before it is turned, so
        that the reference is the scans', not the correction's)."""
        pose = np.asarray(pose, np.float64)
        if self.reference_open:
            self.frames += 1
            m = facade_up(normals_s, pose[:3, :3], self.up)
            if m is not None and np.isfinite(m[1]) and m[1] > 0:
                self.up_sum, self.weight = self.up_sum + m[0] / m[1] ** 2, self.weight + 1.0 / m[1] ** 2
        if self.gain <= 0 or not turn:
            self.stderr.append(0.0 if not turn else float("inf"))
            return pose
        lv = level_rotation(normals_s, pose[:3, :3], self.up)
        w = self.gain * lv.rotvec
        out = pose.copy()
        out[:3, :3] = rotvec_matrix(w) @ pose[:3, :3]
        self.stderr.append(float(lv.stderr) if self.gain >= 1.0 else float("inf"))
        return out

    def precise(self, frame: int) -> bool:
        """Frame `frame`'s levelled tilt is known as well as the up is asked to be (its standard error
        below REFERENCE_STDERR_DEG): the clean streets' scans (~0.3 mdeg), not the noisy ones' (~17)."""
        return self.stderr[frame] < np.radians(REFERENCE_STDERR_DEG)
