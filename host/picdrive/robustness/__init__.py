"""Tolerance studies: the design's firmware on drives drawn from the profile's tolerances (``picdrive robustness``)."""
