"""mcdenoise pipeline: config, channel schema, EXR store, executors and the command line.

Stages (render, clean, train, evaluate) talk to each other only through the store and the
config defined here. Importing this package is cheap: Mitsuba and torch load on demand.
"""
__version__ = "0.1.0"
