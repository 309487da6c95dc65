"""``picdrive console``: the session and its commands (``session``) and the
bench parts it uses (``files``, ``params``, ``plot``, ``record``, ``scope``,
``step``).  Built on the link only."""
