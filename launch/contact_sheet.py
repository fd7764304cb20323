"""One PNG with one row per prompt: sampled motions (or the dataset's clips) as evenly spaced frames.

``python launch/contact_sheet.py --help`` for usage, settings and exit codes; the command line is
pipeline/cli/contact_sheet.py, installed as the ``mfm-contact-sheet`` console script.
"""

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a file from a checkout: import the project, not launch/'s siblings
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from pipeline.cli.contact_sheet import main

if __name__ == "__main__":
    sys.exit(main())
