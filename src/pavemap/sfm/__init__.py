"""Camera poses from plain video (pycolmap SfM made metric by the road): pipeline, scale, steps, checks.

Above :mod:`pavemap.geometry` and :mod:`pavemap.io`, below the commands; pycolmap is imported only when SfM runs.
"""
