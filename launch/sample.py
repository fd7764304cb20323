"""Sample, edit or compose motions with a trained checkpoint.

``python launch/sample.py --help`` for usage, settings and exit codes; the command line is
pipeline/cli/sample.py, installed as the ``mfm-sample`` console script.
"""

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a file from a checkout: import the project, not launch/'s siblings
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from pipeline.cli.sample import main

if __name__ == "__main__":
    sys.exit(main())
