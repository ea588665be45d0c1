"""The ``psonurbs`` command line: parse, call the library, report."""
