"""Applications on top of the engines: the command line, evaluation reports, pictures, video
writing, output sinks, notebook helpers.
"""
