"""Thin entry points (``python launch/<name>.py`` from a checkout, or the ``mfm-*`` console scripts of an install):
each parses its command line and calls the library in ``pipeline``/``preprocess``; nothing else lives here."""
