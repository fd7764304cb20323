"""KIT-ML in HumanML3D's layout (the release HumanML3D's authors distribute: ``new_joints/<id>.npy``
(T, 21, 3) in millimetres at 12.5 fps, ``texts/<id>.txt`` in the same ``caption#tokens#from#to`` format,
``train.txt``/``val.txt``/``test.txt``). The reader is HumanML3D's (``humanml3d.py``); only the dataset
constants differ.

KIT's target skeleton has no published bone lengths: the reference code measures them on clip
``03950`` (``03950_gt``); ``KITSource.target_skeleton()`` does the same on the files at hand.
"""

from __future__ import annotations

from preprocess.sources.humanml3d import HumanML3DLayoutSource


class KITSource(HumanML3DLayoutSource):
    """KIT-ML (21 MMM joints, mm, 12.5 fps). Options as HumanML3D's: joints_dir, splits, default_split."""

    name = "kit"
    skeleton = "kit"
    fps = 12.5
    num_joints = 21
    accepted_joint_counts = (21,)
    reference_clip_ids = ("03950", "03950_gt")
