"""The serial link: the protocol definition and its C renderer
(``protocol``), the Python frame codec (``codec``) and the host client
over any pyserial URL (``client``: ``from picdrive.link.client import Link``)."""
