"""Train the project's evaluator (contrastive motion/text embedding + action classifier).

``python launch/train_evaluator.py --help`` for usage, settings and exit codes; the command line is
pipeline/cli/train_evaluator.py, installed as the ``mfm-train-evaluator`` console script.
"""

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a file from a checkout: import the project, not launch/'s siblings
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from pipeline.cli.train_evaluator import main

if __name__ == "__main__":
    sys.exit(main())
