#!/usr/bin/env python
"""A local nginx serving a folder over HTTP on 127.0.0.1, for the tests and the benchmark of shards behind a
URL (docs/data.md, "Data on a server"). Debian's nginx is installed when missing (as root, with apt-get).

    python scripts/local_nginx.py start --root SHARDS --state DIR [--port N]   # prints http://127.0.0.1:N
    python scripts/local_nginx.py stop --state DIR

Everything nginx writes goes under the state folder: its nginx.conf, pid file, temporary folders, error log and
``access.log`` (one line a request: ``METHOD URI STATUS RANGE BYTES``, where RANGE is the request's Range
header or ``-``). Besides ``/`` the server has three locations over the same folder, for the faults the tests
play: ``/slow/`` sends a shard (``*.tar``) at most ``slow_rate`` bytes a second, ``/crawl/`` at most
``crawl_rate`` (less than a client waiting a second for data accepts), and ``/auth/`` answers 401 to a
request without the header ``Authorization: Bearer TOKEN`` (``--token``). ``stop`` ends only the nginx whose
pid the state folder holds.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

CONF = r"""
daemon off;
master_process off;
pid {state}/nginx.pid;
error_log {state}/error.log warn;
events {{ worker_connections 64; }}
http {{
    log_format plain '$request_method $uri $status "$http_range" $body_bytes_sent';
    access_log {state}/access.log plain;
    client_body_temp_path {state}/tmp/body;
    proxy_temp_path {state}/tmp/proxy;
    fastcgi_temp_path {state}/tmp/fastcgi;
    uwsgi_temp_path {state}/tmp/uwsgi;
    scgi_temp_path {state}/tmp/scgi;
    types {{ application/json json; application/x-tar tar; }}
    default_type application/octet-stream;
    map $uri $slow {{ ~\.tar$ {slow_rate}; default 0; }}
    map $uri $crawl {{ ~\.tar$ {crawl_rate}; default 0; }}
    server {{
        listen 127.0.0.1:{port};
        root {root};
        location /slow/ {{ alias {root}/; limit_rate $slow; }}
        location /crawl/ {{ alias {root}/; limit_rate $crawl; }}
        location /auth/ {{
            alias {root}/;
            if ($http_authorization != "Bearer {token}") {{ return 401; }}
        }}
    }}
}}
"""


def nginx_binary() -> str:
    """The nginx executable; installed from Debian's packages first when missing (root only)."""
    search = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/usr/local/sbin"])
    found = shutil.which("nginx", path=search)
    if found:
        return found
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        raise SystemExit("nginx is not installed; as root: apt-get install -y nginx")
    print("local_nginx: installing nginx (apt-get)", file=sys.stderr, flush=True)
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    wait = ["-o", "DPkg::Lock::Timeout=300"]  # another install (the browser's, SLURM's) may hold the lock
    subprocess.run(["apt-get", *wait, "update", "-qq"], check=True, env=env, stdout=subprocess.DEVNULL)
    subprocess.run(["apt-get", *wait, "install", "-y", "-qq", "nginx"], check=True, env=env,
                   stdout=subprocess.DEVNULL)  # fmt: skip
    if shutil.which("service"):  # the package starts the system's nginx (port 80) where it can: not needed
        subprocess.run(["service", "nginx", "stop"], check=False, capture_output=True)
    found = shutil.which("nginx", path=search)
    if not found:
        raise SystemExit("apt-get installed nginx, but no nginx executable is on the path")
    return found


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Nginx:
    """One nginx serving ``root`` on 127.0.0.1:``port``, its files under ``state``; :meth:`stop` ends the
    process :meth:`start` began, and :meth:`start` again serves on the same port (the access log goes on)."""

    def __init__(self, root: Path, state: Path, port: int | None = None, token: str = "secret",
                 slow_rate: str = "256k", crawl_rate: str = "64") -> None:  # fmt: skip
        self.root, self.state = Path(root).resolve(), Path(state).resolve()
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.binary = nginx_binary()
        self.process: subprocess.Popen | None = None
        (self.state / "tmp").mkdir(parents=True, exist_ok=True)
        conf = CONF.format(state=self.state, port=self.port, root=self.root, token=token, slow_rate=slow_rate,
                           crawl_rate=crawl_rate)  # fmt: skip
        (self.state / "nginx.conf").write_text(conf)

    @property
    def access_log(self) -> Path:
        return self.state / "access.log"

    def requests(self) -> list[tuple[str, str, int, str]]:
        """(method, path, status, Range header or "") of every request served so far."""
        rows = []
        for line in self.access_log.read_text().splitlines() if self.access_log.exists() else ():
            method, uri, status, rest = line.split(" ", 3)
            ranged = rest.rsplit(" ", 1)[0].strip('"')
            rows.append((method, uri, int(status), "" if ranged == "-" else ranged))
        return rows

    def command(self) -> list[str]:
        return [self.binary, "-p", str(self.state), "-c", str(self.state / "nginx.conf"),
                "-e", str(self.state / "error.log")]  # fmt: skip

    def start(self) -> Nginx:
        self.process = subprocess.Popen(self.command(), stdin=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                log = (self.state / "error.log").read_text() if (self.state / "error.log").exists() else ""
                raise RuntimeError(f"nginx exited with status {self.process.returncode}: {log.strip()}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return self
            except OSError:
                time.sleep(0.02)
        self.stop()
        raise RuntimeError(f"nginx did not listen on port {self.port} within 10 s")

    def stop(self) -> None:
        """End the nginx this object started (at once: connections under way are cut)."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process = None

    def __enter__(self) -> Nginx:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("action", choices=("start", "stop"))
    p.add_argument("--state", type=Path, required=True, help="the folder of nginx.conf, logs and pid file")
    p.add_argument("--root", type=Path, help="the folder served (start)")
    p.add_argument("--port", type=int, help="default: a free port")
    p.add_argument("--token", default="secret", help="the bearer token /auth/ accepts")
    a = p.parse_args(argv)
    pid_file = a.state / "nginx.pid"
    if a.action == "stop":
        if pid_file.exists():
            os.kill(int(pid_file.read_text()), signal.SIGTERM)
        return 0
    if a.root is None:
        p.error("start needs --root")
    server = Nginx(a.root, a.state, a.port, a.token)
    subprocess.Popen(server.command(), stdin=subprocess.DEVNULL, start_new_session=True,
                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.monotonic() + 10
    while not pid_file.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    print(server.url)
    return 0


if __name__ == "__main__":
    sys.exit(main())
