"""The papers' claims beside what picdrive computes: ``repro2016``,
``repro2008`` and ``picdrive report`` (``report``)."""
