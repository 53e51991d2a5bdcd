"""A tiny analytic LiDAR for N3 tests: ground plane and two long walls, ray cast in closed form."""
import numpy as np


def corridor_scan(x_sensor: float, *, beams: int = 16, steps: int = 256, height: float = 1.7,
                  half_width: float = 6.0, max_range: float = 30.0) -> np.ndarray:
    """Points [N,3] float32 in the sensor frame of a sensor at (x_sensor, 0, height), looking along +x.
    The scene is the ground z=0 and walls y=+-half_width (world frame); it does not depend on x, so a
    scan at any x is the same in the sensor frame, which is what makes long trajectories cheap."""
    az = np.linspace(-np.pi, np.pi, steps, endpoint=False)
    el = np.deg2rad(np.linspace(-25, 2, beams))
    A, E = np.meshgrid(az, el)
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    t = np.full(len(d), np.inf)
    t = np.minimum(t, np.where(d[:, 2] < -1e-6, -height / d[:, 2], np.inf))
    with np.errstate(divide="ignore"):
        t = np.minimum(t, np.where(np.abs(d[:, 1]) > 1e-6, half_width / np.abs(d[:, 1]), np.inf))
    ok = t < max_range
    return (d[ok] * t[ok, None]).astype(np.float32)


def pose_at(x: float, height: float = 1.7) -> np.ndarray:
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, height
    return T


def hall_scan(sensor_xyz, *, box=None, beams: int = 32, steps: int = 512, half_width: float = 6.0,
              end_x: float = 9.0, max_range: float = 12.0) -> np.ndarray:
    """Points [N,3] float32 in the sensor frame (axes as the world's) of a sensor at `sensor_xyz` in a
    closed hall: the ground z=0, side walls y=+-half_width, end walls x=+-end_x, and optionally a box
    `box = (x0, x1, y0, y1, height)` standing on the ground (world frame), which hides what is behind."""
    boxes = () if box is None else [(box[0], box[1], box[2], box[3], 0.0, box[4])]
    return _trace_hall(sensor_xyz, _directions(beams, steps, 0.0), boxes, half_width, end_x, max_range)


def boxes_scan(sensor_xyz, boxes=(), *, beams: int = 32, steps: int = 512, half_width: float = 6.0,
               end_x: float = 40.0, max_range: float = 60.0) -> np.ndarray:
    """Points [N,3] float32 in the sensor frame (axes as the world's) of a sensor at `sensor_xyz` in a hall
    like `hall_scan`'s (ground z=0, walls y=+-half_width, x=+-end_x) with any number of axis-aligned boxes
    `(x0, x1, y0, y1, z0, z1)` (world frame) in it; returns beyond max_range are lost."""
    return _trace_hall(sensor_xyz, _directions(beams, steps, np.pi / steps), boxes, half_width, end_x, max_range)


def _directions(beams: int, steps: int, az_offset: float) -> np.ndarray:
    """[beams * steps, 3] unit ray directions: `steps` azimuths from -pi (+ az_offset), elevations -25..10 deg."""
    az = np.linspace(-np.pi, np.pi, steps, endpoint=False) + az_offset
    el = np.deg2rad(np.linspace(-25, 10, beams))
    A, E = np.meshgrid(az, el)
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)


def _trace_hall(sensor_xyz, d, boxes, half_width: float, end_x: float, max_range: float) -> np.ndarray:
    """The returns [N, 3] float32 (sensor frame) of rays d [R, 3] from `sensor_xyz` in the hall (ground z=0,
    walls y=+-half_width, x=+-end_x) with axis-aligned boxes (x0, x1, y0, y1, z0, z1); beyond max_range lost."""
    o = np.asarray(sensor_xyz, np.float64)
    t = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.minimum(t, np.where(d[:, 2] < -1e-6, -o[2] / d[:, 2], np.inf))
        for axis, half in ((1, half_width), (0, end_x)):
            for side in (-1.0, 1.0):
                tt = (side * half - o[axis]) / d[:, axis]
                t = np.minimum(t, np.where(tt > 0, tt, np.inf))
        for x0, x1, y0, y1, z0, z1 in boxes:  # slab test against each box
            lo, hi = np.array([x0, y0, z0]), np.array([x1, y1, z1])
            t1, t2 = (lo - o) / d, (hi - o) / d
            near = np.nanmax(np.minimum(t1, t2), axis=1)
            far = np.nanmin(np.maximum(t1, t2), axis=1)
            t = np.minimum(t, np.where((near <= far) & (near > 0), near, np.inf))
    ok = t < max_range
    return (d[ok] * t[ok, None]).astype(np.float32)
