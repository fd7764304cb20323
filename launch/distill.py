"""Make a few-step student of a trained flow-matching checkpoint (reflow on the teacher's own pairs, or a shortcut model).

``python launch/distill.py --help`` for usage, settings and exit codes; the command line is
pipeline/cli/distill.py, installed as the ``mfm-distill`` console script.
"""

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a file from a checkout: import the project, not launch/'s siblings
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from pipeline.cli.distill import main

if __name__ == "__main__":
    sys.exit(main())
