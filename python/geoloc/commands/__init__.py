"""The implementations of the ``geoloc`` commands, one module each.

:mod:`geoloc.cli` holds the argument parsers and registers the commands; each module here
holds what a command does once its options are parsed (``run(args) -> exit status``).
:mod:`._common` has what several share: loading a dataset from ``--dataset/--format``,
frame ranges, progress bars, and localizing a sequence in single or sequential mode;
:mod:`._options` the argparse types and the dataset options of every parser (``geoloc train``'s,
in :mod:`geoloc.training.command`, too).
"""
