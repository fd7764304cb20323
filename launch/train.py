"""Train the MFM flow-matching Transformer.

``python launch/train.py --help`` for usage, settings and exit codes; the command line is
pipeline/cli/train.py, installed as the ``mfm-train`` console script.
"""

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a file from a checkout: import the project, not launch/'s siblings
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from pipeline.cli.train import main

if __name__ == "__main__":
    sys.exit(main())
