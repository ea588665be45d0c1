"""Prepare a cloud: organise it (a local frame, duplicates, neighbourhoods), flag gross
outliers by robust local quadrics, weigh the rest by Tukey's biweight of their distance
to the current fit (``w = (1 - (d / c sigma)^2)^2``), and fit a big cloud on a subsample.
"""
