"""Export a training checkpoint as an inference folder (weights, normalisation, config.json, model card).

``python launch/export.py --help`` for usage, settings and exit codes; the command line is
pipeline/cli/export.py, installed as the ``mfm-export`` console script.
"""

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a file from a checkout: import the project, not launch/'s siblings
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from pipeline.cli.export import main

if __name__ == "__main__":
    sys.exit(main())
