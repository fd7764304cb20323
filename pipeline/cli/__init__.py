"""The command lines of the jobs, one module per command, each with ``main(argv) -> exit code``: the ``mfm-*`` console
scripts of an install, and ``python launch/<name>.py`` in a checkout (launch/ holds one thin file per module here).
The top of the import order: a command may import every part of pipeline/, and nothing imports a command
(tests/test_layout.py)."""
