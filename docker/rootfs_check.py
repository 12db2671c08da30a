"""The steps of docker/check-rootfs.sh that are easier said in Python than in shell.

Standard library only: it runs on the host's ``python3``, not in the project's venv.

``mirror``
    Print the Debian mirror the host's apt uses for bookworm (one-line or deb822 sources).
``replay DOCKERFILE ROOTFS CONTEXT CONFIG``
    Carry out the Dockerfile's instructions in ROOTFS with chroot, as the Docker builder
    would: RUN through ``/bin/sh -c`` in WORKDIR as the current USER with the ENV so far, COPY
    from CONTEXT, and write the final image configuration (ENV, USER, WORKDIR, ENTRYPOINT,
    CMD, HEALTHCHECK) to CONFIG as JSON.
``run ROOTFS CONFIG``
    In a new network namespace (only a loopback, nothing outside reachable), run the image as
    compose does: every shared library resolvable, ``rasterserver demo`` and ``verify``, the
    default command (``serve``) until the Dockerfile's HEALTHCHECK passes, and a Dask scheduler
    and worker that compute a ``process --dask`` job. Prints one ``PASS``/``FAIL`` line per
    check with its time, and exits 1 if any failed.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import shlex
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

#: What ``python:3.11-slim-bookworm`` sets before the Dockerfile's first instruction (its
#: ENV), reproduced by the stand-in: Debian's python3 behind /usr/local/bin/python.
BASE_ENV = {
    "PATH": "/usr/local/bin:/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin",
    "LANG": "C.UTF-8",
}
STAND_IN_FOR = "python:3.11-slim-bookworm"


# ---------------------------------------------------------------------------- mirror


def host_mirror() -> str:
    """The first Debian (not security) mirror in the host's apt sources that has bookworm.

    Returns
    -------
    str
        A mirror URL; ``http://deb.debian.org/debian`` when none is found.
    """
    found: list[tuple[str, list[str]]] = []
    paths = [Path("/etc/apt/sources.list"), *sorted(Path("/etc/apt/sources.list.d").glob("*"))]
    for path in paths:
        if not path.is_file():
            continue
        text = path.read_text(errors="replace")
        if path.suffix == ".sources":
            for stanza in re.split(r"\n\s*\n", text):
                fields = dict(
                    (m.group(1).lower(), m.group(2).split())
                    for m in re.finditer(r"^([A-Za-z-]+):\s*(.*)$", stanza, re.M)
                )
                for uri in fields.get("uris", []):
                    found.append((uri, fields.get("suites", [])))
        else:
            for line in text.splitlines():
                words = [w for w in line.split() if not w.startswith("[")]
                if len(words) >= 3 and words[0] == "deb":
                    found.append((words[1], [words[2]]))
    for uri, suites in found:
        if "bookworm" in suites and "security" not in uri and "/debian" in uri:
            return uri.rstrip("/")
    return "http://deb.debian.org/debian"


# ---------------------------------------------------------------------------- replay


def instructions(dockerfile: Path) -> Iterator[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined, comments dropped."""
    logical = ""
    for raw in dockerfile.read_text().splitlines():
        line = raw.strip()
        if not logical and (not line or line.startswith("#")):
            continue
        if logical and line.startswith("#"):  # a comment inside a continued instruction
            continue
        if line.endswith("\\"):
            logical += line[:-1] + " "
            continue
        logical += line
        keyword, _, rest = logical.partition(" ")
        yield keyword.upper(), rest.strip()
        logical = ""


def expand(value: str, env: dict[str, str]) -> str:
    """Docker's ``$VAR`` / ``${VAR}`` substitution in ENV, WORKDIR and COPY."""
    return re.sub(r"\$\{?([A-Za-z_][A-Za-z0-9_]*)\}?", lambda m: env.get(m.group(1), ""), value)


def parse_env(args: str, env: dict[str, str]) -> dict[str, str]:
    """The ``KEY=VALUE ...`` pairs of an ENV instruction, expanded against ``env``."""
    out: dict[str, str] = {}
    for word in shlex.split(args):
        key, sep, value = word.partition("=")
        if not sep:
            raise SystemExit(f"ENV {args!r}: only the KEY=VALUE form is replayed")
        out[key] = expand(value, {**env, **out})
    return out


def uid_gid(rootfs: Path, user: str) -> tuple[int, int, str]:
    """Numeric uid, gid and home of ``user`` (a name or uid) in the root file system."""
    if user in ("", "root", "0"):
        return 0, 0, "/root"
    for line in (rootfs / "etc/passwd").read_text().splitlines():
        name, _, uid, gid, _, home, _ = line.split(":")
        if user in (name, uid):
            return int(uid), int(gid), home
    raise SystemExit(f"USER {user}: no such account in the image")


def chroot_argv(rootfs: Path, user: str, workdir: str, env: dict[str, str],
                argv: Sequence[str]) -> list[str]:
    """A command line that runs ``argv`` in the image as ``user`` in ``workdir`` with ``env``."""
    uid, gid, home = uid_gid(rootfs, user)
    full_env = {"HOME": home, "HOSTNAME": "rasterserver-check", **env}
    return [
        "chroot", f"--userspec={uid}:{gid}", "--groups=", str(rootfs),
        "/usr/bin/env", "-i", *(f"{k}={v}" for k, v in full_env.items()),
        "/bin/sh", "-c", 'cd "$0" && exec "$@"', workdir, *argv,
    ]


def copy_into(context: Path, sources: Sequence[str], dest: str, rootfs: Path) -> None:
    """COPY: files and folder contents from the build context into the image (as root)."""
    target = rootfs / dest.lstrip("/")
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for source in sources:
        src = context / source
        if not src.exists():
            raise SystemExit(f"COPY {source}: not in the build context {context}")
        if src.is_dir():
            shutil.copytree(src, target, ignore=ignore, dirs_exist_ok=True)
        else:
            into = target / src.name if dest.endswith("/") or len(sources) > 1 else target
            into.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, into)


def build_env() -> dict[str, str]:
    """What the build steps get beside the Dockerfile's ENV, and the image does not keep.

    ``CHECK_ROOTFS_PIP_CERT``: a CA bundle inside the root file system for pip, on a network
    whose proxy re-signs TLS (the check's host gives its own bundle; a Docker build on such
    a network needs the same, e.g. a build secret).
    """
    cert = os.environ.get("CHECK_ROOTFS_PIP_CERT")
    return {"PIP_CERT": cert} if cert else {}


def replay(dockerfile: Path, rootfs: Path, context: Path, config_path: Path) -> int:
    """Carry out the Dockerfile in ``rootfs``; write the image configuration; 0 on success."""
    env = dict(BASE_ENV)
    user, workdir = "root", "/"
    config: dict[str, Any] = {}
    logs = config_path.parent / "build-logs"
    shutil.rmtree(logs, ignore_errors=True)
    logs.mkdir()
    step = 0
    for keyword, args in instructions(dockerfile):
        started = time.monotonic()
        if keyword == "FROM":
            if args.split()[0] != STAND_IN_FOR:
                raise SystemExit(f"FROM {args}: the stand-in root file system is for "
                                 f"{STAND_IN_FOR} only")
        elif keyword == "ENV":
            env.update(parse_env(args, env))
        elif keyword == "WORKDIR":
            workdir = expand(args, env)
            (rootfs / workdir.lstrip("/")).mkdir(parents=True, exist_ok=True)
        elif keyword == "COPY":
            if args.startswith("--"):
                raise SystemExit(f"COPY {args}: options are not replayed")
            *sources, dest = shlex.split(args)
            if not dest.startswith("/"):
                dest = f"{workdir.rstrip('/')}/{dest}"
            copy_into(context, sources, expand(dest, env), rootfs)
        elif keyword == "RUN":
            if args.startswith("["):
                raise SystemExit("RUN in exec form is not replayed")
            step += 1
            log = logs / f"build-step-{step}.log"
            with log.open("wb") as out:
                done = subprocess.run(
                    chroot_argv(rootfs, user, workdir, {**env, **build_env()},
                                ["/bin/sh", "-c", args]),
                    stdout=out, stderr=subprocess.STDOUT,
                )
            if done.returncode != 0:
                print(log.read_text(errors="replace")[-3000:])
                print(f"FAIL  build step RUN {args[:60]}... exit {done.returncode}; log: {log}")
                return 1
        elif keyword == "USER":
            user = args
        elif keyword in ("ENTRYPOINT", "CMD"):
            config[keyword.lower()] = json.loads(args)
        elif keyword == "HEALTHCHECK":
            options, _, command = args.partition("CMD ")
            config["healthcheck"] = json.loads(command)
            config["healthcheck_options"] = options.split()
        elif keyword in ("EXPOSE", "LABEL"):
            config.setdefault(keyword.lower(), []).append(args)
        else:
            raise SystemExit(f"{keyword}: not replayed by this check")
        took = time.monotonic() - started
        if keyword in ("RUN", "COPY"):
            print(f"PASS  build step {keyword} {args[:60]}{'...' if len(args) > 60 else ''}"
                  f"  ({took:.0f} s)", flush=True)
    config.update(env=env, user=user, workdir=workdir)
    config_path.write_text(json.dumps(config, indent=2))
    return 0


# ---------------------------------------------------------------------------- run


def loopback_up() -> None:
    """Bring ``lo`` up in this (new) network namespace, without needing iproute2."""
    siocgifflags, siocsifflags, iff_up = 0x8913, 0x8914, 0x1
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        request = struct.pack("16sH14s", b"lo", 0, b"\0" * 14)
        flags = struct.unpack("16sH14s", fcntl.ioctl(s, siocgifflags, request))[1]
        fcntl.ioctl(s, siocsifflags, struct.pack("16sH14s", b"lo", flags | iff_up, b"\0" * 14))


class Checks:
    """Runs commands in the image and prints one line per check."""

    def __init__(self, rootfs: Path, config: dict[str, Any], logs: Path) -> None:
        self.rootfs, self.config, self.logs = rootfs, config, logs
        self.failed = 0
        self.children: list[subprocess.Popen[bytes]] = []
        self.names: dict[int, str] = {}  # pid -> log name

    def argv(self, argv: Sequence[str], env: dict[str, str] | None = None) -> list[str]:
        return chroot_argv(self.rootfs, self.config["user"], self.config["workdir"],
                           {**self.config["env"], **(env or {})}, argv)

    def report(self, ok: bool, what: str, seconds: float, detail: str = "") -> bool:
        note = f"  {detail}" if detail else ""
        print(f"{'PASS' if ok else 'FAIL'}  {what}  ({seconds:.1f} s){note}", flush=True)
        self.failed += not ok
        return ok

    def run(self, what: str, argv: Sequence[str], *, env: dict[str, str] | None = None,
            timeout: float = 1800, detail: Any = None) -> subprocess.CompletedProcess[str]:
        """Run to completion; PASS on exit 0. ``detail(stdout)`` adds a note to the line."""
        started = time.monotonic()
        log = self.logs / (re.sub(r"\W+", "-", what).strip("-")[:60] + ".log")
        done = subprocess.run(self.argv(argv, env), capture_output=True, text=True,
                              timeout=timeout)
        log.write_text(done.stdout + "\n--- stderr ---\n" + done.stderr)
        note = detail(done.stdout) if detail and done.returncode == 0 else (
            f"exit {done.returncode}; log: {log}" if done.returncode else "")
        self.report(done.returncode == 0, what, time.monotonic() - started, note)
        return done

    def start(self, name: str, argv: Sequence[str], env: dict[str, str] | None = None
              ) -> subprocess.Popen[bytes]:
        """Start a long-running process in the image; its output goes to LOGS/NAME.log."""
        out = (self.logs / f"{name}.log").open("wb")
        child = subprocess.Popen(self.argv(argv, env), stdout=out, stderr=subprocess.STDOUT,
                                 start_new_session=True)
        self.names[child.pid] = name
        self.children.append(child)
        return child

    def healthy(self, what: str, argv: Sequence[str], child: subprocess.Popen[bytes],
                limit: float = 180) -> bool:
        """Repeat a health check command (in the image) until it exits 0 or ``limit`` s pass."""
        started = time.monotonic()
        while time.monotonic() - started < limit:
            if child.poll() is not None:
                return self.report(False, what, time.monotonic() - started,
                                   f"the process exited with {child.returncode}")
            if subprocess.run(self.argv(argv), capture_output=True, timeout=30).returncode == 0:
                return self.report(True, what, time.monotonic() - started)
            time.sleep(1)
        return self.report(False, what, limit, "no healthy answer in time")

    def stop(self, child: subprocess.Popen[bytes], what: str, *, done_line: str = "") -> None:
        """SIGTERM (as ``docker stop`` does) and report the exit code.

        ``done_line``: a line of the log that says the shutdown was orderly; then death by the
        SIGTERM itself passes too (uvicorn re-raises the signal it caught once it has shut
        down, so that its parent sees why it stopped).
        """
        started = time.monotonic()
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGTERM)
        try:
            code = child.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(child.pid, signal.SIGKILL)
            code = child.wait()
        log = (self.logs / f"{self.names[child.pid]}.log").read_text(errors="replace")
        orderly = code == 0 or (code == -signal.SIGTERM and bool(done_line) and done_line in log)
        self.report(orderly, what, time.monotonic() - started,
                    f"exit {code}" + (f", log: {done_line!r}" if done_line in log and done_line
                                      else ""))

    def kill_all(self) -> None:
        for child in self.children:
            if child.poll() is None:
                os.killpg(child.pid, signal.SIGKILL)
                child.wait()


def http_get(url: str) -> str:
    with urllib.request.urlopen(url, timeout=5) as answer:
        return answer.read().decode()


def url_check(url: str) -> list[str]:
    """A health check command, run in the image (as compose.yaml's are)."""
    return ["python", "-c", f"import urllib.request; urllib.request.urlopen({url!r}, timeout=4)"]


def run(rootfs: Path, config_path: Path) -> int:
    """The run-time checks; see the module docstring. 0 when all passed."""
    config = json.loads(config_path.read_text())
    logs = config_path.parent / "logs"
    shutil.rmtree(logs, ignore_errors=True)
    logs.mkdir()
    loopback_up()
    c = Checks(rootfs, config, logs)
    try:
        c.run("python in the image", ["python", "--version"],
              detail=lambda out: out.strip())
        # A library a wheel bundles is found through its loader's RPATH, which ldd on the
        # library alone does not see (scipy's libgfortran and its libquadmath): only names that
        # no wheel bundles must come from the system, i.e. from the Dockerfile's apt packages.
        c.run("every shared library the installed wheels link is in the image (ldd)", [
            "sh", "-c",
            # open3d's torch/tensorflow ops load only with those frameworks (not installed)
            "libs=$(find /opt/venv/lib -name '*.so*' -type f ! -name 'open3d_t*_ops.so'); "
            "bundled=$(for f in $libs; do basename \"$f\"; done | sort -u); "
            "missing=$(for f in $libs; do ldd \"$f\" 2>/dev/null; done "
            "| awk '/not found/ {print $1}' | sort -u | grep -vxF \"$bundled\"); "
            "echo \"$(echo \"$libs\" | wc -l) files, system libraries missing: "
            "${missing:-none}\"; test -z \"$missing\""],
            detail=lambda out: out.strip().splitlines()[-1])
        c.run("import open3d, cv2, h5py and the CLI",
              ["python", "-c", "import open3d, cv2, h5py, rasterserver.cli; "
                               "print('open3d', open3d.__version__)"],
              detail=lambda out: out.strip())
        # the build compiled the chain's loops into the image's numba cache: a fresh process
        # loads them and compiles nothing (numba says "data saved" for what it compiles)
        c.run("a fresh process compiles none of the chain's loops (the image's numba cache)", [
            "sh", "-c",
            "set -e; d=$(mktemp -d); "
            f"{' '.join(config['entrypoint'])} simulate back -o \"$d\" > /dev/null; "
            "NUMBA_DEBUG_CACHE=1 "
            f"{' '.join(config['entrypoint'])} reconstruct \"$d/frame.png\" "
            "--calibration \"$d/calibration.json\" -o \"$d/points.ply\" > \"$d/log\" 2>&1; "
            "loaded=$(grep -c 'data loaded' \"$d/log\" || true); "
            "saved=$(grep -c 'data saved' \"$d/log\" || true); rm -rf \"$d\"; "
            "echo \"$loaded kernels loaded, $saved compiled\"; "
            "test \"$saved\" -eq 0 && test \"$loaded\" -gt 0"],
            detail=lambda out: out.strip().splitlines()[-1])
        c.run("rasterserver demo (SQLite catalogue in /archive, as the image's user)",
              [*config["entrypoint"], "demo"],
              detail=lambda out: f"{len(out.splitlines())} lines of output")
        c.run("rasterserver verify", [*config["entrypoint"], "verify"],
              detail=lambda out: out.strip().splitlines()[-1])
        c.run("archive owner-only", ["sh", "-c", "stat -c '%a %U' /archive; "
                                     "test \"$(stat -c %U /archive)\" = rasterserver"],
              detail=lambda out: out.strip())

        # the image's default command, checked with the Dockerfile's own HEALTHCHECK
        serve = c.start("serve", [*config["entrypoint"], *config["cmd"]])
        if c.healthy(f"`{' '.join(config['entrypoint'] + config['cmd'])}` (default command): "
                     "the Dockerfile's HEALTHCHECK passes", config["healthcheck"], serve):
            port = config["env"].get("RASTERSERVER_PORT", "8000")
            started = time.monotonic()
            try:
                body = http_get(f"http://127.0.0.1:{port}/health")
                c.report('"status":"ok"' in body.replace(" ", ""), "GET /health",
                         time.monotonic() - started, body.strip())
            except OSError as exc:
                c.report(False, "GET /health", time.monotonic() - started, str(exc))
        c.stop(serve, "serve shuts down on SIGTERM", done_line="Finished server process")

        # Dask: scheduler and worker started as compose.yaml starts them, on the loopback
        scheduler = c.start("dask-scheduler", [
            "dask", "scheduler", "--host", "127.0.0.1", "--port", "8786",
            "--dashboard-address", "127.0.0.1:8787"])
        c.healthy("dask scheduler healthy (/health, as compose checks it)",
                  url_check("http://127.0.0.1:8787/health"), scheduler)
        worker = c.start("dask-worker", [
            "dask", "worker", "tcp://127.0.0.1:8786", "--nthreads", "1", "--host", "127.0.0.1",
            "--dashboard-address", "127.0.0.1:8789"])
        c.healthy("dask worker healthy (/health, as compose checks it)",
                  url_check("http://127.0.0.1:8789/health"), worker)
        c.run("simulate and ingest a back to process",
              [*config["entrypoint"], "simulate", "back", "--preset", "severe", "--ingest",
               "--patient", "SIM-DASK", "--seed", "7", "--out", "/tmp/sim-dask"])
        dask_env = {"RASTERSERVER_DASK_SCHEDULER": "tcp://127.0.0.1:8786"}
        c.run("rasterserver process --all-unprocessed --dask (on that scheduler)",
              [*config["entrypoint"], "process", "--all-unprocessed", "--dask"], env=dask_env,
              detail=lambda out: out.strip().splitlines()[-1] if out.strip() else "")
        c.run("the worker computed the stage chains (scheduler's task count)", [
            "python", "-c",
            "from distributed import Client\n"
            "with Client('tcp://127.0.0.1:8786', timeout=10) as client:\n"
            # the engine's tasks are rasterserver.worker.work_batch calls (eight
            # acquisitions each): their key prefix is the function's name
            "    n = client.run_on_scheduler(lambda dask_scheduler: dask_scheduler"
            ".task_prefixes['work_batch'].state_counts['memory'] "
            "if 'work_batch' in dask_scheduler.task_prefixes else 0)\n"
            "print(f'{n} work_batch task(s) finished on the worker')\n"
            "raise SystemExit(0 if n > 0 else 1)"],
            detail=lambda out: out.strip())
        c.run("rasterserver verify after processing", [*config["entrypoint"], "verify"],
              detail=lambda out: out.strip().splitlines()[-1])
        c.stop(worker, "dask worker stops on SIGTERM")
        c.stop(scheduler, "dask scheduler stops on SIGTERM")
    finally:
        c.kill_all()
    print(f"{'ALL PASSED' if not c.failed else f'{c.failed} CHECK(S) FAILED'}", flush=True)
    return 1 if c.failed else 0


def main(argv: Sequence[str]) -> int:
    """Dispatch the subcommands named in the module docstring."""
    if argv[:1] == ["mirror"]:
        print(host_mirror())
        return 0
    if argv[:1] == ["replay"] and len(argv) == 5:
        return replay(Path(argv[1]), Path(argv[2]), Path(argv[3]), Path(argv[4]))
    if argv[:1] == ["run"] and len(argv) == 3:
        return run(Path(argv[1]), Path(argv[2]))
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
