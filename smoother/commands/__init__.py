"""Sub-commands of the ``smoother`` command line, one module each."""
