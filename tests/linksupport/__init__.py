"""Test support for the serial link: builds the rendered C link module with a fake
application (fake_app.c) into a shared library, drives it through ctypes, and serves it
on a local socket so that picdrive.link can be tested against the real C codec."""
