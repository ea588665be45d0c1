"""Running fits: batches and worker processes, the regression gate, the run summary,
scoring a stored surface, pictures and the demo.

May import every layer below it (geometry, fitting, formats, config, errors).
"""
