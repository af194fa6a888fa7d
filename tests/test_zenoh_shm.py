"""The bridge's zenoh session leaves shared memory off, so a peer on the same host does
not set zenoh's ``net`` thread ticking.

With SHM on (zenoh's default) on both sides, establishing the link starts zenoh's SHM
handoff task, a 100 ms loop on its ``net`` runtime that wakes that thread 20 times a
second for the rest of the process's life, whether anything is sent or not
(docs/zenoh.md, "Shared memory off"). The session is built by
:func:`bridge.zenoh.session.open_session` in a child process (zenoh's runtime threads are
per process, and this one runs other sessions); the peer in this process keeps zenoh's
defaults, SHM on, as fleet software on the same host would. A document larger than
zenoh's 3 KiB threshold for moving a payload into SHM still arrives, byte for byte.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import pytest
import zenoh
from zenoh_rig import NO_SCOUTING, free_port, wait_until

pytestmark = pytest.mark.integration  # real zenoh sessions and a child process

#: Voluntary context switches of the child's ``net-*`` threads over one second with the
#: peer connected: 0 here with SHM off; about 20 with it on.
MAX_NET_WAKES = 4
DOCUMENT = bytes(range(256)) * 16  # 4 KiB: above zenoh's SHM threshold (3 KiB)

CHILD = """
import json, os, sys, time
from benchmarks.procstat import thread_stats
from bridge.zenoh.session import ZenohSettings, open_session

settings = ZenohSettings(listen=(sys.argv[1],), overrides=tuple(json.loads(sys.argv[2])))
session, _ = open_session(settings)
pub = session.declare_publisher("test/shm/doc")

def net_wakes():
    stats = thread_stats(os.getpid()).values()
    return sum(vol for name, _, vol, _ in stats if name.startswith("net-"))

print("ready", flush=True)
sys.stdin.readline()  # the peer is connected and subscribed
before = net_wakes()
time.sleep(1.0)  # the observation window
wakes = net_wakes() - before
pub.put(bytes(range(256)) * 16)
print(json.dumps({"net_wakes": wakes}), flush=True)
sys.stdin.readline()
session.close()
"""


def test_a_same_host_peer_with_shm_on_leaves_zenohs_net_thread_asleep() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    overrides = [list(kv) for kv in NO_SCOUTING]
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, endpoint, json.dumps(overrides)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout is not None and child.stdin is not None
        assert child.stdout.readline().strip() == "ready"
        cfg = zenoh.Config()  # zenoh's defaults: shared memory on
        assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is True
        for key, value in NO_SCOUTING:
            cfg.insert_json5(key, value)
        cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
        got: list[bytes] = []
        arrived = threading.Event()

        def on_sample(s: zenoh.Sample) -> None:
            got.append(s.payload.to_bytes())
            arrived.set()

        with zenoh.open(cfg) as peer:
            peer.declare_subscriber("test/shm/**", on_sample)
            wait_until(lambda: any(True for _ in peer.info.peers_zid()), what="the link")
            child.stdin.write("go\n")
            child.stdin.flush()
            report = json.loads(child.stdout.readline())
            assert arrived.wait(10.0), "the document did not arrive"
            child.stdin.write("done\n")
            child.stdin.flush()
            assert child.wait(10.0) == 0
        assert got == [DOCUMENT]
        assert report["net_wakes"] <= MAX_NET_WAKES, report
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(5.0)
