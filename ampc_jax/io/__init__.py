"""Outputs: CSV, JSON and figures of closed-loop runs (:mod:`~.reports`, :mod:`~.figures`)."""
