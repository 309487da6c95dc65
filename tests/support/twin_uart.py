"""Commands to an in-process motor twin through its UART, in simulated time (shared by the tests)."""
from picdrive.link import codec


def command(tw, name, seq, args=None, limit_s=0.1):
    """One command through the twin's UART in simulated time; returns its decoded reply.

    The reply must be an ACK; no reply within ``limit_s`` of simulated time fails the test."""
    tw.uart_write(codec.encode_command(name, seq, args))
    dec, t_end = codec.StreamDecoder(), tw.t + limit_s
    while tw.t < t_end:
        tw.run(1e-3)
        for f in dec.feed(tw.uart_read()):
            if f.is_reply and f.seq == seq:
                assert f.is_ack, (name, f.payload)
                return codec.decode_reply(name, f.payload)
    raise AssertionError(f"no reply to {name} within {limit_s} s of simulated time")
