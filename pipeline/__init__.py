"""mcdenoise pipeline, the core: config, channel schema, EXR store, executors, colour and metrics,
checkpoints, run folders, errors, and the command line.

No module of the core imports a stage (render, clean, train, evaluate) except the command line
(``pipeline.__main__``), which dispatches to them (tests/test_architecture.py checks it). Stages
exchange data through the store and the config defined here. Importing this package is cheap:
Mitsuba and torch load on demand.
"""
__version__ = "0.1.0"
