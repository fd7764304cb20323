"""Convert a published MFM or MDM checkpoint into a checkpoint folder of ours.

``python launch/convert_checkpoint.py --help`` for usage, settings and exit codes; the command line is
pipeline/cli/convert_checkpoint.py, installed as the ``mfm-convert-checkpoint`` console script.
"""

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a file from a checkout: import the project, not launch/'s siblings
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from pipeline.cli.convert_checkpoint import main

if __name__ == "__main__":
    sys.exit(main())
