"""mfm.caption_checks: the synthetic set's clips pass the checks of their own captions (features and all), and a
clip fails the checks of a caption that states another side, count, place or direction."""

from __future__ import annotations

import numpy as np
import pytest

from mfm.caption_checks import caption_check_summary, check_caption, stated_attributes
from mfm.features import features_to_joints, joints_to_features
from mfm.metrics import movement_spread
from mfm.skeleton import HUMANML3D
from preprocess.sources.synthetic import ACTIONS, SyntheticSource

SOURCE = SyntheticSource(num_clips=0)


def clip_of(action: str, seed: int, seconds: float = 6.0):
    """A synthetic clip of ``action`` (regenerated until the source's action draw gives it)."""
    index = seed
    while True:
        clip = SyntheticSource(num_clips=0, actions=[action])._generate(f"synth_{index:06d}", index, seconds)
        if clip.action == action:
            return clip
        index += 1  # pragma: no cover - a single-action source always draws that action


def through_features(joints: np.ndarray) -> np.ndarray:
    """Joints as the judge sees them: through Guo features and back (facing +Z, root above the origin)."""
    return features_to_joints(joints_to_features(joints, HUMANML3D), HUMANML3D)


@pytest.mark.parametrize("action", sorted(ACTIONS))
def test_every_caption_of_a_clip_passes_on_the_clip_itself(action):
    for seed in range(4):
        clip = clip_of(action, seed)
        joints = through_features(clip.joints)
        for caption in clip.captions:
            result = check_caption(joints, caption.text)
            assert result["action"] == action, caption.text
            assert all(result["checks"].values()), (caption.text, result)


def swap_side(caption: str) -> str:
    return caption.replace("left", "@").replace("right", "left").replace("@", "right")


@pytest.mark.parametrize("action", ["wave", "kick", "sidestep", "turn"])
def test_the_other_side_fails(action):
    clip = clip_of(action, 0)
    result = check_caption(through_features(clip.joints), swap_side(clip.captions[0].text))
    assert result["checks"]["side"] is False


def test_a_wrong_count_and_place_fail():
    clip = clip_of("jump", 1)
    joints = through_features(clip.joints)
    stated = stated_attributes(clip.captions[0].text)
    wrong_count = {1: "twice", 2: "3 times", 3: "once"}[stated["count"]]
    other_place = "forward" if stated["place"] == "in_place" else "up in place"
    assert check_caption(joints, f"a person jumps {other_place} {wrong_count}.")["checks"] == {
        "count": False, "place": False}


def test_a_still_body_fails_what_moving_captions_state_and_unknown_captions_are_not_checked():
    still = np.repeat(through_features(clip_of("wave", 0).joints)[:1], 120, axis=0)
    assert check_caption(still, "a person squats down and stands up twice.")["checks"] == {"count": False}
    assert check_caption(still, "a person walks backward slowly.")["checks"] == {"direction": False}
    assert check_caption(still, "a person does a cartwheel.") == {"action": None, "stated": {}, "observed": {},
                                                                    "checks": {}}
    summary = caption_check_summary([still, still], ["a person squats down and stands up twice.",
                                                     "a person does a cartwheel."])["summary"]
    assert summary["count"] == {"share": 0.0, "checked": 1}
    assert summary["all"] == {"share": 0.0, "checked": 1}


def test_movement_spread_counts_the_body_rising_and_sinking_but_not_travel():
    clip = clip_of("wave", 0).joints
    lifted = clip.copy()
    lifted[:, :, 1] += 0.3 * np.sin(np.linspace(0, 6 * np.pi, len(clip)))[:, None]  # the whole body bobs
    travelled = clip.copy()
    travelled[:, :, [0, 2]] += np.linspace(0, 5, len(clip))[:, None, None]  # travel does not count
    base, bobbing, moved = movement_spread(np.stack([clip, lifted, travelled]))
    assert moved == pytest.approx(base, rel=1e-5)  # float32 joints
    assert bobbing > base + 0.15


def test_a_trembling_leg_at_kick_height_counts_as_one_kick():
    clip = through_features(clip_of("kick", 2).joints)
    stated = stated_attributes(clip_of("kick", 2).captions[0].text)
    trembling = clip.copy()
    ankle = 7 if stated["side"] == "left" else 8  # HumanML3D's left/right ankle
    rng = np.random.default_rng(0)
    trembling[:, ankle, 1] += rng.normal(0.0, 0.02, len(clip))  # 2 cm of jitter crossing the threshold often
    assert check_caption(trembling, clip_of("kick", 2).captions[0].text)["observed"]["count"] == stated["count"]


def test_a_turn_reports_its_heading_change_in_degrees():
    for seed in range(4):
        clip = clip_of("turn", seed)
        stated = stated_attributes(clip.captions[0].text)
        observed = check_caption(through_features(clip.joints), clip.captions[0].text)["observed"]
        sign = 1 if stated["side"] == "left" else -1
        assert observed["heading_change_deg"] == pytest.approx(sign * stated["turn_angle"], abs=3), clip.captions[0]


def test_a_turn_past_its_angle_fails():
    """A body spinning in place through 300° has not "turned around": the angle is read to the nearest 90°."""
    pose = clip_of("turn", 0).joints[0]
    centred = pose - pose[:1] * np.array([1.0, 0.0, 1.0])
    frames = []
    for angle in np.radians(np.linspace(0, 300, 80)):
        c, s = np.cos(angle), np.sin(angle)
        yaw = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])  # positive: a turn to the left (Y up)
        frames.append(centred @ yaw.T)
    result = check_caption(np.stack(frames), "a person turns around to the left.")
    assert abs(result["observed"]["heading_change_deg"]) == pytest.approx(300, abs=2)
    assert result["observed"]["turn_angle"] == 270 and result["checks"]["turn_angle"] is False
