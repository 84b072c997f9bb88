"""The commands of the ``testbed`` program: argument parsing and text output, one module per command."""
