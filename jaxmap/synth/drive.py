"""How a sequence of sensor poses drives: heading change, speed and acceleration between frames.

A car's LiDAR at 10 Hz turns a few degrees between two scans (a 6 m corner at 5 m/s: 4.8 deg) and
changes its speed by at most ~0.1 m/s (1 m/s^2); `drive_stats` measures these figures for a trajectory
(the synthetic city writes them into meta.json, "trajectory": "motion", and its tests bound them).

Frames are taken as `frame_rate_hz` apart in time (10 Hz, a spinning LiDAR). Per step i -> i+1 (with
closed=True also the step from the last frame back to the first, as on the synthetic loops):
    yaw change   |heading_{i+1} - heading_i|, the heading being the sensor x axis's direction in the
                 world x-y plane (the drives are planar up to a gentle rocking)
    speed        chord length |t_{i+1} - t_i| * frame_rate_hz
    acceleration change of speed between consecutive steps * frame_rate_hz (longitudinal)
    turn radius  chord / (2 sin(yaw change / 2)): the circle through both positions tangent to both
                 headings (steps that turn less than 1e-6 rad count as straight)
    lateral acceleration  speed * yaw rate
    yaw-rate change  |yaw change_{i+1} - yaw change_i| (deg per frame, per frame): how fast the steering
                 turns. Not bounded here: the synthetic drives join straights and circular arcs, so the yaw
                 change jumps from 0 to a corner's full rate in one frame (a car eases in over ~1 s)
"""
from __future__ import annotations

import numpy as np

FRAME_RATE_HZ = 10.0
# What a car's LiDAR at 10 Hz does between two scans (the bounds the synthetic presets keep).
CAR_MAX_YAW_DEG = 8.0
CAR_MIN_RADIUS_M = 6.0
CAR_MAX_ACCEL_MPS2 = 1.0


def drive_steps(poses, frame_rate_hz: float = FRAME_RATE_HZ, closed: bool = False) -> dict:
    """Per-step figures of poses [n,4,4] (T_world_sensor): {"yaw_deg": [m], "speed_mps": [m],
    "radius_m": [m] (inf where straight), "accel_mps2": [m-1] (closed: [m], cyclic)}, m = n - 1 steps
    (closed: n)."""
    T = np.asarray(poses, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"poses must be [n,4,4], not {list(T.shape)}")
    heading = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    pos = T[:, :3, 3]
    if closed:
        heading, pos = np.r_[heading, heading[:1]], np.concatenate([pos, pos[:1]])
    dyaw = np.abs((np.diff(heading) + np.pi) % (2 * np.pi) - np.pi)
    chord = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    speed = chord * frame_rate_hz
    with np.errstate(divide="ignore"):
        radius = np.where(dyaw > 1e-6, chord / (2 * np.sin(np.maximum(dyaw, 1e-12) / 2)), np.inf)
    dv = np.diff(np.r_[speed, speed[:1]]) if closed else np.diff(speed)
    return {"yaw_deg": np.degrees(dyaw), "speed_mps": speed, "radius_m": radius,
            "accel_mps2": dv * frame_rate_hz}


def drive_stats(poses, frame_rate_hz: float = FRAME_RATE_HZ, closed: bool = False) -> dict:
    """The extremes of `drive_steps` (rounded, for meta.json): frame_rate_hz, max_yaw_deg_per_frame,
    min_turn_radius_m (None when the drive never turns), min/max_speed_mps, max_accel_mps2 (|longitudinal|),
    max_lateral_accel_mps2 and max_yaw_rate_change_deg (see the module docstring). A single pose has no
    steps: only frame_rate_hz."""
    out = {"frame_rate_hz": float(frame_rate_hz)}
    if len(poses) < 2:
        return out
    s = drive_steps(poses, frame_rate_hz, closed)
    r_min = float(s["radius_m"].min())
    lateral = s["speed_mps"] * np.radians(s["yaw_deg"]) * frame_rate_hz
    out.update(max_yaw_deg_per_frame=round(float(s["yaw_deg"].max()), 4),
               min_turn_radius_m=round(r_min, 3) if np.isfinite(r_min) else None,
               min_speed_mps=round(float(s["speed_mps"].min()), 4),
               max_speed_mps=round(float(s["speed_mps"].max()), 4),
               max_accel_mps2=round(float(np.abs(s["accel_mps2"]).max()), 4) if len(s["accel_mps2"]) else 0.0,
               max_lateral_accel_mps2=round(float(lateral.max()), 3),
               max_yaw_rate_change_deg=round(float(np.abs(np.diff(s["yaw_deg"])).max()), 4)
               if len(s["yaw_deg"]) > 1 else 0.0)
    return out


def is_car_like(stats: dict) -> bool:
    """Whether drive_stats' figures keep the bounds of a car at 10 Hz (CAR_MAX_YAW_DEG, CAR_MIN_RADIUS_M,
    CAR_MAX_ACCEL_MPS2)."""
    if "max_yaw_deg_per_frame" not in stats:
        return True
    r = stats["min_turn_radius_m"]
    return (stats["max_yaw_deg_per_frame"] <= CAR_MAX_YAW_DEG and (r is None or r >= CAR_MIN_RADIUS_M)
            and stats["max_accel_mps2"] <= CAR_MAX_ACCEL_MPS2)
