"""Applications on top of the engines: the command line, evaluation reports, pictures, video and
bag I/O, output sinks, progress.
"""
