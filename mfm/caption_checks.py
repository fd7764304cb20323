"""Does a motion do what its caption states? Checks for the procedural set's captions (``--source synthetic``).

The synthetic set's captions state attributes a pooled sentence embedding barely separates ("waves with the left
hand" and "... right hand" have cosine 0.98 under MiniLM): the side, the number of repetitions, in place or forward,
the direction of travel and of a turn. A plausibility figure cannot tell whether a sample heard them; these checks
read each one off the joints (HumanML3D's 22-joint skeleton, metres, Y up, the first frame facing +Z as recovered
from Guo features) and compare it with what the caption says:

=============  ==============================================  ===================================================
attribute      caption                                         read off the joints
=============  ==============================================  ===================================================
side           waves with the left hand; kicks with the        which wrist rises above the head most (wave); which
               right leg; steps sideways to the left; turns    ankle lifts most (kick); the sign of the sideways
               to the right                                    travel (sidestep) or of the heading change (turn)
count          once / twice / N times (jump, squat, kick,      jumps: flight phases (both feet off the floor);
               raise_arms)                                     squats: dips of the pelvis; kicks: lifts of the
                                                               named ankle; arm raises: both wrists over the head
place          jumps up in place / forward                     horizontal travel of the pelvis
direction      walks forward / backward; runs forward          travel along the first frame's facing direction
turn_angle     turns 90 degrees / turns around                 heading change, to the nearest multiple of 90°
=============  ==============================================  ===================================================

Each check is ``None`` when the caption does not state that attribute (e.g. "someone kicks with their left foot"
gives no count). The thresholds are fractions of what the synthetic generator draws (a jump's flight lifts the
feet 0.35 m, a squat lowers the pelvis about 0.4 m, a kick lifts the ankle about 0.5 m); ground-truth clips pass
every check (tested), so a failed check on a sample is the sample's. This is our own judge for our own procedural
captions, not a published metric.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from mfm.skeleton import HUMANML3D

_J = {name: i for i, name in enumerate(HUMANML3D.joint_names)}
ATTRIBUTES = ("side", "count", "place", "direction", "turn_angle")
_COUNT_WORDS = {"once": 1, "twice": 2}

# What the generator draws, and the fraction of it that counts as "done" (see the module docstring).
FLIGHT_CLEARANCE_M = 0.12  # both feet this far above their standing height: in the air (flight peak 0.35 m)
SQUAT_DIP_M = 0.15  # pelvis this far below its standing height: a squat (about 0.4 m at the bottom)
KICK_LIFT_M = 0.2  # ankle this far above its standing height: a kick (about 0.5 m at the top)
IN_PLACE_M = 0.3  # horizontal pelvis travel below this: in place (a forward jump travels 0.9 m per jump)
TRAVEL_M = 0.2  # sideways / forward travel that decides a direction
ARMS_UP_M = 0.07  # both wrists this far above the neck: arms raised (0.14 m at the top)


def _count(text: str) -> int | None:
    match = re.search(r"\b(once|twice|(\d+) times)\b", text)
    if match is None:
        match = re.search(r"\bdoes (\d+) squats\b", text)
        return int(match.group(1)) if match else None
    return _COUNT_WORDS.get(match.group(1)) or int(match.group(2))


def _side(text: str) -> str | None:
    match = re.search(r"\b(left|right)\b", text)
    return match.group(1) if match else None


def stated_attributes(caption: str) -> dict[str, Any]:
    """The action and the attributes a synthetic-set caption states (``{}`` for a caption of another kind)."""
    text = caption.lower()
    if "wave" in text:
        return {"action": "wave", "side": _side(text)}
    if "kick" in text:
        return {"action": "kick", "side": _side(text), "count": _count(text)}
    if "jump" in text:
        place = "in_place" if "in place" in text else "forward" if "forward" in text else None
        return {"action": "jump", "count": _count(text), "place": place}
    if "squat" in text:
        return {"action": "squat", "count": _count(text)}
    if "arms" in text and ("raise" in text or "lift" in text):
        return {"action": "raise_arms", "count": _count(text)}
    if "sideways" in text or "shuffles" in text:
        return {"action": "sidestep", "side": _side(text)}
    if "turns" in text and "walk" not in text:
        angle = 180 if "around" in text else 90 if "90" in text else None
        return {"action": "turn", "side": _side(text), "turn_angle": angle}
    if "walk" in text or "run" in text:
        direction = "backward" if "backward" in text else "forward" if ("forward" in text or "ahead" in text) else None
        return {"action": "run" if "run" in text else "walk", "direction": direction}
    return {}


def _segments(signal: np.ndarray, threshold: float, min_frames: int = 2) -> int:
    """How many times ``signal`` rises above ``threshold`` for at least ``min_frames`` frames, with hysteresis: a
    rise ends only when the signal falls below half the threshold, so jitter around the threshold (a generated leg
    trembling at kick height) counts once, as a person watching would count it, while a real lowering in between
    counts twice."""
    count, above, run = 0, False, 0
    for value in signal:
        if not above and value > threshold:
            above, run = True, 0
        elif above and value < threshold / 2:
            above = False
            count += run >= min_frames
        run += above
    return int(count + (above and run >= min_frames))


def _standing(height: np.ndarray) -> float:
    """A joint's standing height: the median over the clip's first and last 10 % (motions start and end at rest)."""
    edge = max(1, len(height) // 10)
    return float(np.median(np.concatenate([height[:edge], height[-edge:]])))


def _facing(joints: np.ndarray, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit horizontal (forward, left) vectors of one frame, from the hips (left hip minus right hip points left)."""
    across = joints[frame, _J["left_hip"]] - joints[frame, _J["right_hip"]]
    left = np.array([across[0], 0.0, across[2]])
    left /= max(np.linalg.norm(left), 1e-9)
    forward = np.cross(left, np.array([0.0, 1.0, 0.0]))  # left × up = forward (right-handed, Y up)
    return forward, left


def _forward_directions(joints: np.ndarray) -> np.ndarray:
    """(T, 3) unit horizontal forward vector of every frame (see :func:`_facing`)."""
    across = joints[:, _J["left_hip"]] - joints[:, _J["right_hip"]]
    left = np.stack([across[:, 0], np.zeros(len(across)), across[:, 2]], axis=1)
    left /= np.maximum(np.linalg.norm(left, axis=1, keepdims=True), 1e-9)
    return np.cross(left, np.array([0.0, 1.0, 0.0]))


def _heading_change(joints: np.ndarray) -> float:
    """Signed heading change in degrees over the clip, summed frame to frame so that a half turn keeps its sign
    (positive: turned left, as the generator's heading)."""
    forward = _forward_directions(joints)
    steps = np.arctan2(np.cross(forward[:-1], forward[1:])[:, 1], np.sum(forward[:-1] * forward[1:], axis=1))
    return float(np.degrees(steps.sum()))


def observed_attributes(joints: np.ndarray, action: str) -> dict[str, Any]:
    """What a (T, 22, 3) motion shows for the attributes of ``action`` (the keys :func:`stated_attributes` gives)."""
    joints = np.asarray(joints, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (22, 3):
        raise ValueError(f"caption checks need (T, 22, 3) HumanML3D joints, got {joints.shape}")
    pelvis = joints[:, _J["pelvis"]]
    travel = pelvis[-1] - pelvis[0]
    _, left = _facing(joints, 0)
    if action == "wave":
        above = {s: joints[:, _J[f"{s}_wrist"], 1] - joints[:, _J["head"], 1] for s in ("left", "right")}
        return {"side": max(above, key=lambda s: float(np.percentile(above[s], 75)))}
    if action == "kick":
        lift = {s: joints[:, _J[f"{s}_ankle"], 1] - _standing(joints[:, _J[f"{s}_ankle"], 1]) for s in ("left", "right")}
        side = max(lift, key=lambda s: float(lift[s].max()))
        return {"side": side, "count": _segments(lift[side], KICK_LIFT_M)}
    if action == "jump":
        feet = joints[:, [_J["left_ankle"], _J["right_ankle"]], 1]
        clearance = feet.min(axis=1) - min(_standing(feet[:, 0]), _standing(feet[:, 1]))
        horizontal = float(np.hypot(travel[0], travel[2]))
        return {"count": _segments(clearance, FLIGHT_CLEARANCE_M),
                "place": "in_place" if horizontal < IN_PLACE_M else "forward"}
    if action == "squat":
        dip = _standing(pelvis[:, 1]) - pelvis[:, 1]
        return {"count": _segments(dip, SQUAT_DIP_M)}
    if action == "raise_arms":
        above = np.minimum(joints[:, _J["left_wrist"], 1], joints[:, _J["right_wrist"], 1]) - joints[:, _J["neck"], 1]
        return {"count": _segments(above, ARMS_UP_M)}
    if action == "sidestep":
        sideways = float(travel @ left)
        return {"side": None if abs(sideways) < TRAVEL_M else "left" if sideways > 0 else "right"}
    if action == "turn":
        change = _heading_change(joints)
        # The nearest multiple of 90°: a 300° spin is not "turns around", nor a 30° glance "turns 90 degrees".
        return {"side": "left" if change > 0 else "right", "turn_angle": int(90 * round(abs(change) / 90)),
                "heading_change_deg": round(change, 1)}  # what the check rounded, for a study of the misses
    if action in ("walk", "run"):
        # Travel along each frame's own facing, so that a walk in a curve still counts as forward.
        along = float(np.sum(np.diff(pelvis, axis=0) * _forward_directions(joints)[:-1]))
        return {"direction": None if abs(along) < TRAVEL_M else "forward" if along > 0 else "backward"}
    raise ValueError(f"no caption checks for action {action!r}")


def check_caption(joints: np.ndarray, caption: str) -> dict[str, Any]:
    """``{"action", "stated", "observed", "checks": {attribute: True/False}}`` for one motion and its caption;
    ``checks`` holds only the attributes the caption states (empty for a caption these checks do not know)."""
    stated = stated_attributes(caption)
    if not stated:
        return {"action": None, "stated": {}, "observed": {}, "checks": {}}
    action = stated.pop("action")
    observed = observed_attributes(joints, action)
    checks = {key: observed.get(key) == value for key, value in stated.items() if value is not None}
    return {"action": action, "stated": stated, "observed": observed, "checks": checks}


def caption_check_summary(motions: Sequence[np.ndarray], captions: Sequence[str]) -> dict[str, Any]:
    """Per attribute, the share of motions whose caption states it that show it (and how many were checked), and
    ``all``: the share of checked motions that pass every check of their caption."""
    if len(motions) != len(captions):
        raise ValueError(f"{len(motions)} motions for {len(captions)} captions")
    rows = [check_caption(m, c) for m, c in zip(motions, captions)]
    summary: dict[str, Any] = {}
    for attribute in ATTRIBUTES:
        passed = [row["checks"][attribute] for row in rows if attribute in row["checks"]]
        if passed:
            summary[attribute] = {"share": float(np.mean(passed)), "checked": len(passed)}
    checked = [all(row["checks"].values()) for row in rows if row["checks"]]
    summary["all"] = {"share": float(np.mean(checked)) if checked else None, "checked": len(checked)}
    return {"summary": summary, "rows": rows}
