"""Applications on top of the engines: the command line (``cli``, one module per command in
``commands``), evaluation reports, pictures, video writing, output sinks, notebook helpers.
"""
