"""Results people can look at: BVH files for Blender, stick-figure videos, contact sheets (many motions on one
PNG), plots of the x̂1 estimates along an ODE trajectory (MFM Figure 4) and MDM's results.npy (for MDM's
SMPL-fitting and mesh-rendering scripts)."""

from mfm.export.bvh import BVHJoint, BVHMotion, read_bvh, write_bvh
from mfm.export.contact_sheet import render_contact_sheet
from mfm.export.mdm_results import MDMResults, read_mdm_results, write_mdm_results
from mfm.export.plots import estimates_to_joints, plot_x1_trajectory
from mfm.export.render import ffmpeg_available, render_motion
from mfm.export.stick import EDITED_COLOR, KEPT_COLOR, Camera

__all__ = [
    "BVHJoint",
    "BVHMotion",
    "Camera",
    "EDITED_COLOR",
    "KEPT_COLOR",
    "MDMResults",
    "estimates_to_joints",
    "ffmpeg_available",
    "plot_x1_trajectory",
    "read_bvh",
    "read_mdm_results",
    "render_contact_sheet",
    "render_motion",
    "write_bvh",
    "write_mdm_results",
]
