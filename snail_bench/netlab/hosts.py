"""TCP on the lab's hosts, tuned as an operator would tune real ones, inside the lab's
namespaces only (each network namespace has its own ``net.ipv4`` settings).

- ``congestion``: the congestion control on every lab route (``ip route ... congctl``;
  this kernel refuses ``net.ipv4.tcp_congestion_control`` inside a namespace). A route's
  choice overrides a socket's own, so it also overrides the cubic the service asks for
  on links with a client at one end (snail_common/net/conn.py);
- ``slow_start_after_idle``: ``net.ipv4.tcp_slow_start_after_idle``;
- ``buffer_bytes``: the largest socket buffers TCP may grow to (the third value of
  ``net.ipv4.tcp_wmem`` and ``tcp_rmem``), never below the kernel's own: a stream whose
  send buffer is under the link's bandwidth-delay product cannot fill the link (a new
  namespace allows 4 MiB; 1 Gbit/s over 80 ms round trips needs 10 MB).

None keeps the kernel's default. ``tcp_settings`` reads back what is in force.
"""

from __future__ import annotations

import re

from .namespaces import LINKS, ROLES, Lab, _run


def tune_tcp(lab: Lab, congestion: str | None = None,
             slow_start_after_idle: bool | None = None,
             buffer_bytes: int | None = None) -> None:
    """Set the lab's hosts' TCP (module doc) before any daemon connects."""
    for role in ROLES:
        ns = lab.ns[role]
        if slow_start_after_idle is not None:
            _sysctl(ns, "net.ipv4.tcp_slow_start_after_idle", str(int(slow_start_after_idle)))
        if buffer_bytes is not None:
            for name in ("net.ipv4.tcp_wmem", "net.ipv4.tcp_rmem"):
                low, default, high = _run("ip", "netns", "exec", ns, "sysctl", "-n",
                                          name).split()
                if buffer_bytes > int(high):
                    _sysctl(ns, name, f"{low} {default} {buffer_bytes}")
        if congestion is None:
            continue
        for link, pair in LINKS.items():
            if role not in pair:
                continue
            peer = pair[1 - pair.index(role)]
            prefix = lab.address(link, role).rsplit(".", 1)[0] + ".0/24"
            _run("ip", "-n", ns, "route", "replace", prefix, "dev",
                 lab.ifname(role, peer), "proto", "kernel", "scope", "link",
                 "src", lab.address(link, role), "congctl", congestion)


def tcp_settings(lab: Lab) -> dict[str, object]:
    """The client's congestion control and slow-start-after-idle, as TCP will use them on
    the lab's links, and the garbler's largest send buffer (measured, not asked for)."""
    ns = lab.ns["client"]
    route = _run("ip", "-n", ns, "route", "show", "dev", lab.ifname("client", "evaluator"))
    congctl = re.search(r"congctl (\S+)", route)
    default = _run("ip", "netns", "exec", ns, "sysctl", "-n",
                   "net.ipv4.tcp_congestion_control").strip()
    idle = _run("ip", "netns", "exec", ns, "sysctl", "-n",
                "net.ipv4.tcp_slow_start_after_idle").strip()
    wmem = _run("ip", "netns", "exec", lab.ns["garbler"], "sysctl", "-n",
                "net.ipv4.tcp_wmem").split()
    return {"congestion_control": congctl.group(1) if congctl else default,
            "slow_start_after_idle": idle == "1", "send_buffer_max": int(wmem[2])}


def bdp_buffer(shapes: dict, rtt_floor_s: float = 0.001) -> int:
    """Socket buffers for the lab's links: twice the largest bandwidth-delay product of
    its shaped links (a rate and a delay both set), 0 if none has both."""
    largest = 0.0
    for shape in shapes.values():
        if shape.rate_mbit and shape.delay_ms:
            rtt = max(2 * shape.delay_ms / 1000, rtt_floor_s)
            largest = max(largest, shape.rate_mbit * 1e6 / 8 * rtt)
    return int(2 * largest)


def _sysctl(ns: str, name: str, value: str) -> None:
    _run("ip", "netns", "exec", ns, "sysctl", "-q", "-w", f"{name}={value}")
