"""Evaluate checkpoints (text/action-to-motion metrics, editing, composition) with 95 % CIs.

``python launch/evaluate.py --help`` for usage, settings and exit codes; the command line is
pipeline/cli/evaluate.py, installed as the ``mfm-evaluate`` console script.
"""

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a file from a checkout: import the project, not launch/'s siblings
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from pipeline.cli.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
