import os
from pathlib import Path

import pytest

# No model hub or dataset site at run time: fail fast instead of retrying downloads.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("WANDB_MODE", "disabled")

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = Path(os.environ.get("MFM_SHARED_DIR", REPO_ROOT.parent / "shared"))
REFERENCE_DATA = SHARED_DIR / "reference-data"


@pytest.fixture
def reference_data() -> Path:
    """The real HumanML3D clip and normalisation files (../shared/reference-data)."""
    if not REFERENCE_DATA.is_dir():
        pytest.skip(f"reference data not found at {REFERENCE_DATA} (set MFM_SHARED_DIR or place shared/ beside the checkout)")
    return REFERENCE_DATA
