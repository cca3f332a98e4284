"""What the two command-line programs (``lrfcal``, ``lrfsim``) share on the terminal: the typer app's settings, usage
lines, errors as one line and an exit code (:mod:`.cliutil`), and the progress display of the long jobs
(:mod:`.progress`). Above the method (the progress line names the calibration's stages); lrfsim reaches them
through lrfcal's public API (``from lrfcal import make_app, progress_display, ...``).

Nothing is imported here: each module is imported by its own name.
"""
