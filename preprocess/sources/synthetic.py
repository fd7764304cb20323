"""Procedural clips on HumanML3D's 22-joint target skeleton, for tests and smoke runs at any size.

Every clip is forward kinematics of simple periodic joint angles over ``HUMANML3D.target_offsets()``
(so its bone lengths are HumanML3D's), a heading and a velocity in the facing frame; the root height
keeps the lowest foot joint 5 cm above the floor (plus a flight height for jumps). Actions: walk, run,
jump, wave, turn, squat, kick, raise_arms, sidestep, each with parameters (speed, side, direction,
count) that its captions state ("a person walks forward slowly", "someone waves with the right hand").

Determinism: clip ``i`` depends only on ``(seed, i)`` (numpy's seeded generator), not on ``num_clips``,
so a bigger dataset extends a smaller one. Lengths are drawn in ``[min_seconds, max_seconds]`` at 20 fps;
the defaults (2-9.9 s: 41-199 frames, 40-198 feature frames) pass HumanML3D's length filter. Splits come
from a hash of the id (80/10/10).

Bad input for tests (option ``corrupt``, e.g. ``["nan", "bad_shape"]``): each kind adds one item
``corrupt_<kind>`` that goes through the same checks as real data:
``nan``/``inf`` (a few frames hold NaN/inf -> skipped ``nan_frames``), ``bad_shape`` (21 joints ->
skipped ``bad_shape``), ``no_captions`` (-> skipped ``no_captions``), ``short`` (0.5 s) and ``long``
(15 s): valid clips the processing stage filters as too_short/too_long. Unreadable files need a file:
tests write them in a HumanML3D layout instead.

Conventions: the character faces +Z at heading 0 and its left is +X (HumanML3D's rest pose); a joint's
rotation turns the bones of its children; positive heading turns left.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from mfm.rotations import axis_angle_to_matrix
from mfm.skeleton import HUMANML3D
from preprocess.clip import NO_CAPTIONS, Caption, Clip, SkippedInput, check_joints
from preprocess.sources.humanml3d import as_name_list, hash_split

FPS = 20.0
FOOT_JOINTS = (7, 8, 10, 11)
FOOT_CLEARANCE = 0.05  # metres between the floor and the lowest foot joint
CORRUPTIONS = ("nan", "inf", "bad_shape", "no_captions", "short", "long")
_CORRUPT_INDEX_BASE = 10**9
JOINT_INDEX = {name: i for i, name in enumerate(HUMANML3D.joint_names)}
X, Y, Z = np.eye(3)


@dataclass
class MotionPlan:
    """What an action produces: per-frame joint rotations (axis-angle, T x 22 x 3), heading (T,) in
    radians, velocity (T, 3) in the facing frame (m/s), flight height (T,) and its captions."""

    rotations: np.ndarray
    heading: np.ndarray
    velocity: np.ndarray
    flight: np.ndarray
    captions: list[str]

    @classmethod
    def still(cls, frames: int) -> "MotionPlan":
        return cls(np.zeros((frames, 22, 3)), np.zeros(frames), np.zeros((frames, 3)), np.zeros(frames), [])

    def rotate(self, joint: str, axis: np.ndarray, angle: np.ndarray | float) -> None:
        """Add a rotation about a fixed ``axis`` of the joint's parent frame (angles in radians)."""
        self.rotations[:, JOINT_INDEX[joint]] += np.asarray(angle, dtype=np.float64).reshape(-1, 1) * axis


def _phase(frames: int, hertz: float, rng: np.random.Generator) -> np.ndarray:
    return 2 * math.pi * hertz * np.arange(frames) / FPS + rng.uniform(0, 2 * math.pi)


def _envelope(frames: int, ramp_seconds: float = 0.4) -> np.ndarray:
    """0 -> 1 -> 0 over the clip with cosine ramps, so motions start and end at rest."""
    ramp = min(int(ramp_seconds * FPS), frames // 2)
    env = np.ones(frames)
    if ramp > 0:
        rise = 0.5 - 0.5 * np.cos(np.linspace(0, math.pi, ramp))
        env[:ramp], env[frames - ramp :] = rise, rise[::-1]
    return env


def _bumps(frames: int, count: int) -> np.ndarray:
    """``count`` smooth 0 -> 1 -> 0 bumps spread over the clip (for squats, jumps, kicks)."""
    t = np.linspace(0, 1, frames)
    return np.sin(math.pi * (t * count % 1.0)) ** 2


def _times(count: int) -> str:
    return {1: "once", 2: "twice"}.get(count, f"{count} times")


def _gait(plan: MotionPlan, phase: np.ndarray, hip: float, knee: float, arm: float, elbow: float, env: np.ndarray) -> None:
    """Alternating legs and opposite arms (walk, run, sidestep in place of the leg swing)."""
    for side, offset in (("left", 0.0), ("right", math.pi)):
        swing = np.sin(phase + offset)
        plan.rotate(f"{side}_hip", X, -hip * swing * env)
        plan.rotate(f"{side}_knee", X, knee * np.clip(np.sin(phase + offset + 1.2), 0, None) * env + 0.05)
        plan.rotate(f"{side}_shoulder", X, arm * swing * env)  # opposite to the leg on that side
        plan.rotate(f"{side}_elbow", X, -elbow)


# ----------------------------------------------------------------------------------------------------
# Actions: (rng, frames) -> plan with captions
# ----------------------------------------------------------------------------------------------------


def walk(rng: np.random.Generator, frames: int) -> MotionPlan:
    pace, speed, hertz = [("slowly", 0.6, 1.4), ("at a normal pace", 1.1, 1.8), ("quickly", 1.5, 2.1)][rng.integers(3)]
    backward = rng.random() < 0.2
    turn = 0.0 if backward else float(rng.choice([0.0, 0.0, 0.5, -0.5]))  # rad/s
    plan, env = MotionPlan.still(frames), _envelope(frames)
    _gait(plan, _phase(frames, hertz, rng), hip=0.45, knee=0.9, arm=0.35, elbow=0.2, env=env)
    plan.velocity[:, 2] = (-speed if backward else speed) * env
    plan.heading = np.cumsum(turn * env) / FPS
    direction = "backward" if backward else "forward"
    extra = "" if turn == 0 else f" while turning {'left' if turn > 0 else 'right'}"
    plan.captions = [
        f"a person walks {direction} {pace}{extra}.",
        f"someone is walking {direction} {pace}{extra}.",
    ]
    if turn != 0:
        plan.captions.append(f"a person walks in a curve to the {'left' if turn > 0 else 'right'}.")
    return plan


def run(rng: np.random.Generator, frames: int) -> MotionPlan:
    pace, speed = [("at a jog", 2.2), ("fast", 3.2)][rng.integers(2)]
    plan, env = MotionPlan.still(frames), _envelope(frames)
    _gait(plan, _phase(frames, 2.8, rng), hip=0.7, knee=1.6, arm=0.6, elbow=1.4, env=env)
    plan.rotate("spine1", X, 0.2 * env)  # lean into the run
    plan.velocity[:, 2] = speed * env
    plan.captions = [f"a person runs forward {pace}.", f"someone is running straight ahead {pace}."]
    return plan


def jump(rng: np.random.Generator, frames: int, forward_share: float = 0.5) -> MotionPlan:
    """``forward_share``: the probability that a jump travels forward rather than up in place; the draw is made
    whatever it is, so changing it changes only which jumps travel, not any other clip."""
    count, forward = int(rng.integers(1, 4)), bool(rng.random() < forward_share)
    plan = MotionPlan.still(frames)
    t = np.linspace(0, 1, frames) * count % 1.0
    crouch = np.where(t < 0.35, np.sin(math.pi * t / 0.35) ** 2, 0) + np.where(t > 0.75, np.sin(math.pi * (t - 0.75) / 0.25) ** 2, 0)
    air = (t >= 0.35) & (t <= 0.75)
    plan.flight = np.where(air, 0.35 * np.sin(math.pi * (t - 0.35) / 0.4), 0.0)
    for side in ("left", "right"):
        plan.rotate(f"{side}_hip", X, -1.0 * crouch)
        plan.rotate(f"{side}_knee", X, 1.6 * crouch)
        plan.rotate(f"{side}_shoulder", X, np.where(air, -2.4, 0.6 * crouch))  # swing back, then up
    plan.rotate("spine1", X, 0.4 * crouch)
    if forward:
        plan.velocity[:, 2] = np.where(air, 1.5, 0.0)
    where = "forward" if forward else "up in place"
    plan.captions = [f"a person jumps {where} {_times(count)}.", f"someone crouches and jumps {where} {_times(count)}."]
    return plan


def wave(rng: np.random.Generator, frames: int) -> MotionPlan:
    side = ["right", "left"][rng.integers(2)]
    sign = -1.0 if side == "right" else 1.0  # abduction is about -Z on the right, +Z on the left
    plan, env = MotionPlan.still(frames), _envelope(frames, 0.6)
    plan.rotate(f"{side}_shoulder", Z, sign * 2.5 * env)
    plan.rotate(f"{side}_elbow", Z, sign * (0.4 + 0.45 * np.sin(_phase(frames, 2.0, rng))) * env)
    plan.captions = [
        f"a person waves with the {side} hand.",
        f"someone raises their {side} arm and waves.",
        f"a person stands still and waves {side}-handed.",
    ]
    return plan


def turn(rng: np.random.Generator, frames: int) -> MotionPlan:
    side = ["left", "right"][rng.integers(2)]
    degrees = [90, 180][rng.integers(2)]
    plan, env = MotionPlan.still(frames), _envelope(frames, 0.3)
    rate = env / env.sum() * math.radians(degrees) * (1 if side == "left" else -1)
    plan.heading = np.cumsum(rate)
    _gait(plan, _phase(frames, 1.6, rng), hip=0.2, knee=0.5, arm=0.1, elbow=0.2, env=env)
    around = "turns around" if degrees == 180 else "turns 90 degrees"
    plan.captions = [f"a person {around} to the {side}.", f"someone turns to their {side} in place."]
    return plan


def squat(rng: np.random.Generator, frames: int) -> MotionPlan:
    count = int(rng.integers(1, 4))
    plan, down = MotionPlan.still(frames), _bumps(frames, count)
    for side in ("left", "right"):
        plan.rotate(f"{side}_hip", X, -1.4 * down)
        plan.rotate(f"{side}_knee", X, 2.0 * down)
        plan.rotate(f"{side}_shoulder", X, -1.3 * down)  # arms forward for balance
    plan.rotate("spine1", X, 0.5 * down)
    plan.captions = [f"a person squats down and stands up {_times(count)}.", f"someone does {count} squats."]
    return plan


def kick(rng: np.random.Generator, frames: int) -> MotionPlan:
    side, count = ["right", "left"][rng.integers(2)], int(rng.integers(1, 3))
    plan, lift = MotionPlan.still(frames), _bumps(frames, count)
    plan.rotate(f"{side}_hip", X, -1.3 * lift)
    plan.rotate(f"{side}_knee", X, 1.2 * np.sin(math.pi * lift) ** 2)  # chamber, then extend
    plan.rotate("spine1", X, -0.2 * lift)
    plan.captions = [f"a person kicks forward with the {side} leg {_times(count)}.", f"someone kicks with their {side} foot."]
    return plan


def raise_arms(rng: np.random.Generator, frames: int) -> MotionPlan:
    count = int(rng.integers(1, 3))
    plan, up = MotionPlan.still(frames), _bumps(frames, count)
    plan.rotate("left_shoulder", Z, 2.8 * up)
    plan.rotate("right_shoulder", Z, -2.8 * up)
    plan.captions = [
        f"a person raises both arms above the head and lowers them {_times(count)}.",
        "someone lifts their arms up over their head.",
    ]
    return plan


def sidestep(rng: np.random.Generator, frames: int) -> MotionPlan:
    side = ["left", "right"][rng.integers(2)]
    plan, env = MotionPlan.still(frames), _envelope(frames)
    phase = _phase(frames, 1.5, rng)
    for leg, offset in (("left", 0.0), ("right", math.pi)):
        plan.rotate(f"{leg}_hip", Z, (1 if leg == "left" else -1) * 0.25 * np.clip(np.sin(phase + offset), 0, None) * env)
    plan.velocity[:, 0] = (0.5 if side == "left" else -0.5) * env  # left is +X
    plan.captions = [f"a person steps sideways to the {side}.", f"someone shuffles to their {side}."]
    return plan


ACTIONS: dict[str, Callable[[np.random.Generator, int], MotionPlan]] = {
    f.__name__: f for f in (walk, run, jump, wave, turn, squat, kick, raise_arms, sidestep)
}


# ----------------------------------------------------------------------------------------------------
# Plan -> joints
# ----------------------------------------------------------------------------------------------------

_OFFSETS = HUMANML3D.target_offsets()
_PARENTS = HUMANML3D.parents
_HAS_CHILDREN = frozenset(int(p) for p in _PARENTS[1:])
# The target skeleton's raw neck->head direction is forward (+Z); tip it up so the head sits above the
# neck as in real HumanML3D clips.
_HEAD_TILT = -math.radians(75.0)


def _yaw_matrices(heading: np.ndarray) -> np.ndarray:
    c, s = np.cos(heading), np.sin(heading)
    out = np.zeros((heading.size, 3, 3))
    out[:, 0, 0], out[:, 0, 2], out[:, 1, 1], out[:, 2, 0], out[:, 2, 2] = c, s, 1.0, -s, c
    return out


def plan_to_joints(plan: MotionPlan) -> np.ndarray:
    """(T, 22, 3) positions in metres, Y up: forward kinematics of the plan's rotations, turned by its
    heading, moved by its integrated velocity, and lifted so the feet stand on the floor."""
    rotations = plan.rotations.copy()
    rotations[:, JOINT_INDEX["neck"]] += _HEAD_TILT * X
    # Only joints that rotate and have children need matrices (this is most of the cost).
    moving = [j for j in range(22) if j in _HAS_CHILDREN and np.any(rotations[:, j])]
    local = dict(zip(moving, axis_angle_to_matrix(torch.from_numpy(rotations[:, moving])).unbind(1)))
    yaw = _yaw_matrices(plan.heading)
    frames = rotations.shape[0]
    world = {0: yaw @ local[0].numpy() if 0 in local else yaw}
    positions = np.zeros((frames, 22, 3))
    for joint in range(1, 22):  # parents come before children in HumanML3D's order
        parent = _PARENTS[joint]
        positions[:, joint] = positions[:, parent] + world[parent] @ _OFFSETS[joint]
        if joint in _HAS_CHILDREN:
            world[joint] = world[parent] @ local[joint].numpy() if joint in local else world[parent]
    travel = np.cumsum(np.einsum("tij,tj->ti", yaw, plan.velocity), axis=0) / FPS
    lowest_foot = positions[:, FOOT_JOINTS, 1].min(axis=1)
    travel[:, 1] = FOOT_CLEARANCE - lowest_foot + plan.flight
    return positions + travel[:, None, :]


# ----------------------------------------------------------------------------------------------------
# The source
# ----------------------------------------------------------------------------------------------------


class SyntheticSource:
    """Procedural HumanML3D-skeleton clips (see the module docstring).

    Options: ``num_clips`` (default 100), ``seed`` (default 0), ``min_seconds``/``max_seconds`` (2/9.9),
    ``actions`` (a subset of ACTIONS, default all), ``corrupt`` (kinds from CORRUPTIONS, default none),
    ``jump_forward_share`` (the share of jumps that travel forward, default 0.5; 0: every jump is "up in place",
    the set otherwise clip for clip the same: an ablation of what the forward jumps teach the in-place ones).
    """

    name = "synthetic"
    skeleton = "humanml3d"

    def __init__(
        self,
        root: str | None = None,
        *,
        num_clips: int | str = 100,
        seed: int | str = 0,
        min_seconds: float | str = 2.0,
        max_seconds: float | str = 9.9,
        actions: str | Sequence[str] | None = None,
        corrupt: str | Sequence[str] = (),
        jump_forward_share: float | str = 0.5,
    ) -> None:
        if root is not None:
            raise ValueError(f"synthetic: takes no root folder (got {root!r}); it generates its clips")
        self.num_clips = int(num_clips)
        self.seed = int(seed)
        self.min_seconds, self.max_seconds = float(min_seconds), float(max_seconds)
        if self.num_clips < 0:
            raise ValueError(f"synthetic: num_clips must be >= 0, got {num_clips!r}")
        if not 0.5 <= self.min_seconds <= self.max_seconds:
            raise ValueError(f"synthetic: need 0.5 <= min_seconds <= max_seconds, got {min_seconds!r}, {max_seconds!r}")
        self.jump_forward_share = float(jump_forward_share)
        if not 0.0 <= self.jump_forward_share <= 1.0:
            raise ValueError(f"synthetic: jump_forward_share must be in [0, 1], got {jump_forward_share!r}")
        self.actions = as_name_list(actions) or tuple(ACTIONS)
        unknown = sorted(set(self.actions) - set(ACTIONS))
        if unknown:
            raise ValueError(f"synthetic: unknown action(s) {unknown}; known: {list(ACTIONS)}")
        self.corrupt = as_name_list(corrupt)
        unknown = sorted(set(self.corrupt) - set(CORRUPTIONS))
        if unknown:
            raise ValueError(f"synthetic: unknown corruption(s) {unknown}; known: {list(CORRUPTIONS)}")

    def list_items(self) -> list[str]:
        return [f"synth_{i:06d}" for i in range(self.num_clips)] + sorted(f"corrupt_{kind}" for kind in set(self.corrupt))

    def load(self, item: str) -> Clip | SkippedInput:
        if item.startswith("corrupt_"):
            return self._corrupted(item, item.removeprefix("corrupt_"))
        return self._generate(item, int(item.removeprefix("synth_")), seconds=None)

    def _generate(self, item: str, index: int, seconds: float | None) -> Clip:
        rng = np.random.default_rng([self.seed, index])
        action = self.actions[int(rng.integers(len(self.actions)))]
        if seconds is None:
            seconds = float(rng.uniform(self.min_seconds, self.max_seconds))
        options = {"forward_share": self.jump_forward_share} if action == "jump" else {}
        plan = ACTIONS[action](rng, int(round(seconds * FPS)) + 1, **options)
        return Clip(
            id=item,
            joints=plan_to_joints(plan).astype(np.float32),
            fps=FPS,
            skeleton=self.skeleton,
            captions=[Caption(text) for text in plan.captions],
            split=hash_split(item),
            source=self.name,
            action=action,
            path=f"synthetic:{self.seed}:{item}",
        )

    def _corrupted(self, item: str, kind: str) -> Clip | SkippedInput:
        """A deliberately bad item; it goes through the same checks as real input."""
        if kind not in self.corrupt:
            raise ValueError(f"synthetic: item {item!r} is not one of this source's corruptions {self.corrupt}")
        seconds = {"short": 0.5, "long": 15.0}.get(kind, 3.0)
        # Indices past any real clip's keep corrupt items independent of num_clips.
        clip = self._generate(item, index=_CORRUPT_INDEX_BASE + CORRUPTIONS.index(kind), seconds=seconds)
        joints = clip.joints.copy()
        if kind == "nan":
            joints[5:8, 3] = np.nan
        elif kind == "inf":
            joints[2, 0, 1] = np.inf
        elif kind == "bad_shape":
            joints = joints[:, :21]
        elif kind == "no_captions":
            return SkippedInput(item, clip.path, NO_CAPTIONS, "generated without captions")
        problem = check_joints(joints, HUMANML3D.num_joints)
        if problem is not None:
            return SkippedInput(item, clip.path, *problem)
        clip.joints = joints
        return clip
