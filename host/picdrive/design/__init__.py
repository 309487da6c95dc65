"""Design methods (``fuzzy_hinf``, ``mixed_pid``, ``zn``, ``ga``), the
verifier every design passes (``verify``) and the method dispatch
(``dispatch``).  Imports analysis, models and the core; never the firmware,
the link or the twin."""
