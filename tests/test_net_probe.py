"""The link probe: its rate span skips slow start, and a loopback measurement is sane."""

import socket
import threading

from snail_bench.netlab import probe


def test_the_rate_is_taken_over_the_second_half_of_the_blast():
    # slow start: 1 MB in the first second, then 10 MB/s: the late half sees only the latter
    arrivals = [(0.0, 0), (1.0, 1_000_000), (2.0, 11_000_000), (3.0, 21_000_000)]
    assert probe.rate_span(arrivals) == (10_000_000, 1.0)


def test_a_blast_whose_second_half_saw_nothing_uses_its_whole_span():
    assert probe.rate_span([(0.0, 0), (2.0, 5_000_000)]) == (5_000_000, 2.0)
    assert probe.rate_span([(0.0, 0)]) == (0, 0.0)
    assert probe.rate_span([]) == (0, 0.0)


def test_a_loopback_measurement_reports_a_round_trip_and_a_rate():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    threading.Thread(target=probe.serve, args=("127.0.0.1", port), daemon=True).start()
    for _ in range(100):  # the server's listener may take a moment
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            threading.Event().wait(0.02)
    result = probe.measure("127.0.0.1", port, pings=3, seconds=0.2)
    assert result["rtt_ms"] > 0 and result["rate_mbit"] > 0  # figures: the bench's to judge
