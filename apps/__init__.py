"""apps: the programs a person runs: the demo, live gaze preview and dataset redirection.

May import: anything (toolkit, render, geometry, train).
"""
