"""The local Ray instance of ``--executor ray`` listens on loopback only: every TCP or UDP socket
bound by Ray's processes (GCS, raylet, workers, agents, and the driver's own server) has a
127.0.0.0/8 or ::1 address, read from /proc (Linux)."""

from __future__ import annotations

import ipaddress
import os
import time
from pathlib import Path

import pytest

PROC = Path("/proc")
LISTEN, UDP_UNCONNECTED = "0A", "07"  # /proc/net/tcp* and udp* socket states


def _address(hex_addr: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    """An address of /proc/net/{tcp,udp}[6]: 32-bit words in host (little-endian) order."""
    raw = bytes.fromhex(hex_addr)
    return ipaddress.ip_address(b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4)))


def _is_loopback(addr: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    mapped = getattr(addr, "ipv4_mapped", None)
    return addr.is_loopback or (mapped is not None and mapped.is_loopback)


def _bound_sockets() -> dict[int, tuple[str, str, int]]:
    """Socket inode -> (protocol, address, port) of every listening TCP and unconnected UDP socket."""
    out = {}
    for proto, state in (("tcp", LISTEN), ("tcp6", LISTEN), ("udp", UDP_UNCONNECTED), ("udp6", UDP_UNCONNECTED)):
        path = PROC / "net" / proto
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == state:
                host, port = f[1].split(":")
                out[int(f[9])] = (proto, str(_address(host)), int(port, 16))
    return out


def _descendants(pid: int) -> set[int]:
    parent = {}
    for d in PROC.iterdir():
        try:
            parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (ValueError, OSError, IndexError):
            continue
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p and c not in found]
        found.update(kids)
        todo.extend(kids)
    return found


def _socket_inodes(pid: int) -> set[int]:
    inodes = set()
    try:
        for fd in (PROC / str(pid) / "fd").iterdir():
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(int(target[8:-1]))
    except OSError:
        pass
    return inodes


def _name(pid: int) -> str:
    try:
        return (PROC / str(pid) / "comm").read_text().strip()
    except OSError:
        return "?"


@pytest.mark.skipif(not (PROC / "net" / "tcp").exists(), reason="reads /proc/net (Linux)")
def test_the_local_ray_instance_listens_on_loopback_only():
    ray = pytest.importorskip("ray")
    from n2f2.distributed import RayExecutor

    if ray.is_initialized():
        pytest.skip("Ray is already running in this process")
    from ray._private import ray_constants

    enabled = ray_constants.ENABLE_RAY_CLUSTER
    me = os.getpid()
    mine_before = _socket_inodes(me)  # the driver's sockets that are not Ray's
    with RayExecutor(num_cpus=1) as executor:
        assert sorted(executor.map(abs, [-1, -2])) == [(0, 1), (1, 2)]
        assert ray_constants.ENABLE_RAY_CLUSTER == enabled  # switched off for ray.init only
        time.sleep(3)  # the dashboard and runtime-env agents start beside the first task
        bound = _bound_sockets()
        owners = {i: p for p in _descendants(me) for i in _socket_inodes(p)}
        owners.update({i: me for i in _socket_inodes(me) - mine_before})
        ray_sockets = [(_name(owners[i]), owners[i], *bound[i]) for i in owners if i in bound]
    names = {name for name, *_ in ray_sockets}
    assert {"gcs_server", "raylet"} <= names, f"Ray's servers not found: {sorted(names)}"
    exposed = sorted(
        f"{name} (pid {pid}) {proto} {addr}:{port}"
        for name, pid, proto, addr, port in ray_sockets
        if not _is_loopback(ipaddress.ip_address(addr))
    )
    assert not exposed, "Ray listens beyond this machine: " + "; ".join(exposed)
