"""``picdrive console``: the session (``session``), its commands (``commands``) and the
bench parts it uses (``files``, ``params``, ``plot``, ``record``, ``scope``,
``step``).  Built on the link only."""
