"""The local Ray instance a sweep starts listens on 127.0.0.1 only: Ray's ports run code for whoever reaches them."""
from __future__ import annotations

import ipaddress
import os

import pytest

from pvslam_core.sweep import executors as X


def _ray_listeners() -> list[str]:
    """Addresses the processes started by this one (Ray's GCS, raylet, workers, agents) listen on."""
    import psutil

    found = []
    for proc in psutil.Process(os.getpid()).children(recursive=True):
        try:
            conns = proc.net_connections(kind="inet")
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
        found += [c.laddr.ip for c in conns if c.status == psutil.CONN_LISTEN]
    return found


def _loopback(ip: str) -> bool:
    addr = ipaddress.ip_address(ip.split("%")[0])
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        addr = addr.ipv4_mapped
    return addr.is_loopback


def test_the_local_ray_instance_listens_on_loopback_only():
    ray = pytest.importorskip("ray")
    pytest.importorskip("psutil")
    if ray.is_initialized():
        pytest.skip("a Ray instance is already running in this process")
    ex = X.RayExecutor(workers=1, threads=1)
    try:
        assert ex.owned and ray.util.get_node_ip_address() == "127.0.0.1"
        listeners = _ray_listeners()
        assert listeners, "no Ray process found listening"
        assert all(_loopback(ip) for ip in listeners), listeners
    finally:
        ex.close()
    assert not ray.is_initialized()


def test_the_loopback_request_and_an_address_are_passed_through(monkeypatch):
    """What the executor asks of ray.init, checked with a stand-in (also where Ray is not installed)."""
    import sys
    import types

    calls = []
    fake = types.ModuleType("ray")
    fake.is_initialized = lambda: False
    fake.init = lambda **kw: calls.append(kw)
    fake.cluster_resources = lambda: {"CPU": 2}
    fake.nodes = lambda: [{"Alive": True, "Resources": {"CPU": 2}}]
    fake.remote = lambda fn: fn
    fake.util = types.SimpleNamespace(get_node_ip_address=lambda: "127.0.0.1")
    monkeypatch.setitem(sys.modules, "ray", fake)
    X.RayExecutor(workers=2, threads=1)
    assert calls[-1]["_node_ip_address"] == "127.0.0.1" and calls[-1]["include_dashboard"] is False
    X.RayExecutor(address="ray://head:10001")  # an existing cluster: its own addresses, nothing forced
    assert calls[-1]["address"] == "ray://head:10001" and "_node_ip_address" not in calls[-1]

