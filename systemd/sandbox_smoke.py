#!/usr/bin/env python3
"""Run the daemon under an approximation of the unit's sandbox, where systemd cannot run it.

A development check (root, Linux >= 6.3, x86_64, util-linux's unshare/setpriv, the kernel
headers): it re-creates, without systemd, the sandbox directives that could break numpy,
pyserial or zenoh at run time, runs ``compass-bridge run`` on the built-in simulated compass
with MAVLink and a loopback zenoh peer for a few seconds under a fake notify socket, and
reports whether it streamed, pinged the watchdog and stopped cleanly.

What is re-created (and how):

* ``ProtectSystem=strict``, ``PrivateTmp``: a mount namespace with ``/`` read-only, a
  fresh tmpfs on ``/tmp``, only the state directory writable;
* ``ProtectProc=invisible``, ``ProcSubset=pid``: a new pid namespace with its own procfs
  mounted ``hidepid=invisible,subset=pid``;
* ``User=``, ``CapabilityBoundingSet=`` (empty), ``NoNewPrivileges``: ``setpriv``;
* ``MemoryDenyWriteExecute=yes``: ``prctl(PR_SET_MDWE)`` (the kernel's own W^X switch);
* ``SystemCallFilter=~@privileged @resources`` (EPERM) and ``RestrictAddressFamilies=``
  (EAFNOSUPPORT): a seccomp filter built here from ``systemd-analyze syscall-filter``.

Not re-created: the ``@system-service`` allow-list (only the deny-lists above are
enforced), ``DevicePolicy``/``DeviceAllow`` (the simulated compass needs no device), the
``Protect*`` directives for kernel tunables, modules, logs and the clock.

Usage:  sudo python3 systemd/sandbox_smoke.py [SECONDS]
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HEADER = Path("/usr/include/x86_64-linux-gnu/asm/unistd_64.h")
ALLOWED_FAMILIES = (socket.AF_UNIX, socket.AF_INET, socket.AF_INET6, socket.AF_NETLINK)
DENIED_GROUPS = ("@privileged", "@resources")

# seccomp / BPF constants (linux/seccomp.h, linux/filter.h, linux/audit.h)
PR_SET_NO_NEW_PRIVS, PR_SET_SECCOMP, SECCOMP_MODE_FILTER = 38, 22, 2
PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN = 65, 1
SECCOMP_RET_ALLOW, SECCOMP_RET_ERRNO, SECCOMP_RET_KILL_PROCESS = 0x7FFF0000, 0x00050000, 0x80000000
AUDIT_ARCH_X86_64 = 0xC000003E
BPF_LD_W_ABS, BPF_JEQ_K, BPF_RET_K = 0x20, 0x15, 0x06
EPERM, EAFNOSUPPORT = 1, 97


def syscall_numbers() -> dict[str, int]:
    text = HEADER.read_text()
    return {m[1]: int(m[2]) for m in re.finditer(r"#define __NR_(\w+)\s+(\d+)", text)}


def expand(groups: tuple[str, ...]) -> set[str]:
    """Syscall names of systemd's groups (nested groups expanded), as the installed systemd defines them."""
    out: set[str] = set()
    todo = list(groups)
    while todo:
        g = todo.pop()
        text = subprocess.run(
            ["systemd-analyze", "syscall-filter", g], capture_output=True, text=True, check=True
        ).stdout
        for word in text.split():
            if word.startswith("#") or word == g:
                continue
            if word.startswith("@"):
                todo.append(word)
            else:
                out.add(word)
    return out


def seccomp_program(denied: list[int], socket_nr: int) -> bytes:
    """A classic BPF program: wrong arch -> kill; socket(family not allowed) -> EAFNOSUPPORT;
    a denied syscall -> EPERM; anything else allowed."""

    def stmt(code: int, k: int) -> bytes:
        return struct.pack("HBBI", code, 0, 0, k)

    def jeq(k: int, jt: int, jf: int) -> bytes:
        return struct.pack("HBBI", BPF_JEQ_K, jt, jf, k)

    prog = [
        stmt(BPF_LD_W_ABS, 4),  # seccomp_data.arch
        jeq(AUDIT_ARCH_X86_64, 1, 0),
        stmt(BPF_RET_K, SECCOMP_RET_KILL_PROCESS),
        stmt(BPF_LD_W_ABS, 0),  # seccomp_data.nr
    ]
    # socket(): check args[0] (the family; low 32 bits at offset 16)
    fam = [stmt(BPF_LD_W_ABS, 16)]
    for i, f in enumerate(ALLOWED_FAMILIES):
        left = len(ALLOWED_FAMILIES) - i  # jump over the remaining checks + the errno return
        fam.append(jeq(f, left, 0))
    fam.append(stmt(BPF_RET_K, SECCOMP_RET_ERRNO | EAFNOSUPPORT))
    fam.append(stmt(BPF_RET_K, SECCOMP_RET_ALLOW))
    prog.append(jeq(socket_nr, 0, len(fam)))
    prog += fam
    for nr in denied:
        prog.append(jeq(nr, 0, 1))
        prog.append(stmt(BPF_RET_K, SECCOMP_RET_ERRNO | EPERM))
    prog.append(stmt(BPF_RET_K, SECCOMP_RET_ALLOW))
    return b"".join(prog)


def confine_and_exec(argv: list[str]) -> None:
    """In the sandboxed child: MDWE, seccomp, then exec the daemon."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN, 0, 0, 0) != 0:
        sys.exit(f"PR_SET_MDWE failed (errno {ctypes.get_errno()}): kernel older than 6.3?")
    nrs = syscall_numbers()
    denied = sorted(nrs[n] for n in json.loads(os.environ.pop("SMOKE_DENIED")) if n in nrs)
    prog = seccomp_program(denied, nrs["socket"])
    buf = ctypes.create_string_buffer(prog)

    class SockFprog(ctypes.Structure):
        _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]

    fprog = SockFprog(len(prog) // 8, ctypes.addressof(buf))
    if libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
        sys.exit("PR_SET_NO_NEW_PRIVS failed")
    if libc.prctl(PR_SET_SECCOMP, SECCOMP_MODE_FILTER, ctypes.byref(fprog), 0, 0) != 0:
        sys.exit(f"seccomp filter refused (errno {ctypes.get_errno()})")
    os.execv(argv[0], argv)


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--confined":
        confine_and_exec(sys.argv[2:])
        return 1  # not reached
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 8.0
    if os.geteuid() != 0:
        sys.exit("run as root (it builds namespaces)")
    binary = shutil.which("compass-bridge") or str(Path(sys.executable).parent / "compass-bridge")
    python = os.path.realpath(sys.executable)
    work = Path(tempfile.mkdtemp(prefix="cb-sandbox-", dir="/var/tmp"))
    state = work / "state"
    state.mkdir()
    shutil.chown(state, "nobody", "nogroup")
    zport = 17447 + os.getpid() % 1000
    cfg = work / "bridge.toml"
    cfg.write_text(
        '[device]\nport = "sim"\n\n[mavlink]\nendpoints = ["udpout:127.0.0.1:14599"]\n\n'
        f'[zenoh]\nenabled = true\nlisten = ["tcp/127.0.0.1:{zport}"]\nmulticast_scouting = false\n\n'
        f'[storage]\ndir = "{state}"\n'
    )
    os.chmod(work, 0o755)
    os.chmod(cfg, 0o644)
    name = f"cb-sandbox-{os.getpid()}"
    mgr = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    mgr.bind("\0" + name)
    mgr.settimeout(0.2)
    denied = sorted(expand(DENIED_GROUPS))
    # The service user is an ordinary uid. If this Python lives where nobody cannot reach it
    # (pyenv under /root), fall back to uid 0 *without any capability*: still no way past
    # file modes of others' files, the read-only mounts or the filters.
    reach = subprocess.run(
        ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups", "test", "-x", python],
        check=False,
    )
    user = "--reuid=nobody --regid=nogroup" if reach.returncode == 0 else "--reuid=0 --regid=0"
    inner = (
        "set -e; mount --make-rprivate /; "
        "mount -t proc -o hidepid=invisible,subset=pid proc /proc; "
        "mount -t tmpfs tmpfs /tmp; "
        f"mount --bind {state} {state}; "
        "mount -o remount,bind,ro /; "
        f"exec setpriv {user} --clear-groups --no-new-privs "
        "--inh-caps=-all --bounding-set=-all -- "
        f"{python} {Path(__file__).resolve()} --confined {binary} -v run --config {cfg}"
    )
    env = dict(
        os.environ,
        NOTIFY_SOCKET="@" + name,
        WATCHDOG_USEC="2000000",
        SMOKE_DENIED=json.dumps(denied),
        OPENBLAS_NUM_THREADS="1",
    )
    log = open(work / "daemon.log", "wb")  # noqa: SIM115
    # --kill-child: when unshare dies, the daemon (pid 1 of the new namespace) gets SIGTERM,
    # as systemd's stop would send it.
    proc = subprocess.Popen(
        ["unshare", "--mount", "--pid", "--fork", "--kill-child=SIGTERM", "--", "sh", "-c", inner],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=log,
    )
    msgs: list[str] = []

    def pump(until: float, stop_on: str = "") -> None:
        while time.monotonic() < until:
            try:
                msgs.append(mgr.recv(4096).decode())
            except TimeoutError:
                continue
            if stop_on and stop_on in msgs[-1]:
                return

    try:
        pump(time.monotonic() + seconds)
        # Stop it as systemd would: SIGTERM to the main pid (the daemon, pid 1 of the
        # namespace; unshare does not forward signals). It must be gone within 5 s.
        main_pid = subprocess.run(
            ["pgrep", "-f", f"compass-bridge -v run --config {cfg}"],
            capture_output=True,
            text=True,
        ).stdout.split()
        t0 = time.monotonic()
        for pid in main_pid:
            os.kill(int(pid), 15)
        pump(t0 + 5, "STOPPING=1")
        stopped = any("STOPPING=1" in m for m in msgs)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(max(0.1, t0 + 5 - time.monotonic()))
        left = [] if proc.poll() is not None else main_pid
        for pid in left:  # still there after 5 s: not a clean stop
            os.kill(int(pid), 9)
    finally:
        if proc.poll() is None:
            proc.kill()
        log.close()
    text = (work / "daemon.log").read_text(errors="replace")
    ready = [m for m in msgs if "READY=1" in m]
    pings = sum("WATCHDOG=1" in m for m in msgs)
    statuses = [m for m in msgs if m.startswith("STATUS=") and " Hz" in m]
    who = "nobody" if reach.returncode == 0 else "uid 0 without capabilities"
    print(f"seccomp deny-list: {len(denied)} syscalls; MDWE on; caps none; user {who}")
    print(f"READY: {ready[0] if ready else 'NO'}")
    print(f"last STATUS: {statuses[-1] if statuses else 'none'}")
    print(f"WATCHDOG pings: {pings}; STOPPING sent: {stopped}; exited within 5 s: {not left}")
    problems = [ln for ln in text.splitlines() if "ERROR" in ln or "Traceback" in ln]
    for needed in ("mavlink: system", "zenoh: session"):  # both outputs came up
        if needed not in text:
            problems.append(f"no {needed!r} line: that output did not start")
    print("log problems:" if problems else "log: no errors")
    for ln in problems[:20]:
        print("  " + ln)
    ok = bool(ready) and pings > 0 and bool(statuses) and stopped and not left and not problems
    print("SANDBOX SMOKE:", "OK" if ok else f"FAILED (log: {work / 'daemon.log'})")
    if ok:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
