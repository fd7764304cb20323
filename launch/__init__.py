"""Thin entry points for a checkout: ``python launch/<name>.py`` (or ``accelerate launch launch/train.py``) runs
``pipeline/cli/<name>.py``'s ``main``, which an install runs as the ``mfm-*`` console scripts. Not installed: only
the library packages (mfm, pipeline, preprocess) are (tests/test_packaging.py)."""
