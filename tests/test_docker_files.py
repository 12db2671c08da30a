"""The invariants of docker/: what the image needs, how it is built, how compose runs it.

No Docker engine runs here, so these read the files; docker/check-rootfs.sh builds and runs
the image's root file system (too slow for the test suite; its results are in
docs/deployment.md).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import struct
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest
import yaml
from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

DOCKER = Path(__file__).resolve().parents[1] / "docker"
REPO = DOCKER.parent

#: Debian packages in every Debian image (Priority: required), python:3.11-slim-bookworm too.
DEBIAN_BASE = {"libc6", "libgcc-s1", "libstdc++6", "zlib1g"}


def instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of docker/Dockerfile, continuation lines joined."""
    out: list[tuple[str, str]] = []
    logical = ""
    for raw in (DOCKER / "Dockerfile").read_text().splitlines():
        line = raw.strip()
        if line.startswith("#") or (not line and not logical):
            continue
        if line.endswith("\\"):
            logical += line[:-1] + " "
            continue
        keyword, _, rest = (logical + line).partition(" ")
        out.append((keyword.upper(), " ".join(rest.split())))
        logical = ""
    return out


def apt_packages() -> set[str]:
    """The packages the Dockerfile's ``apt-get install`` lines install."""
    packages: set[str] = set()
    for keyword, args in instructions():
        if keyword != "RUN":
            continue
        for command in re.split(r"&&|;", args):
            words = shlex.split(command)
            if words[:2] == ["apt-get", "install"]:
                packages |= {w for w in words[2:] if not w.startswith("-")}
    return packages


def constraints() -> dict[str, tuple[str, str]]:
    """docker/constraints.txt: canonical name -> (name as written, version)."""
    pins: dict[str, tuple[str, str]] = {}
    for line in (DOCKER / "constraints.txt").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        match = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([0-9][A-Za-z0-9.+!-]*)", line)
        assert match, f"constraints.txt: {line!r} is not an exact pin NAME==VERSION"
        name = canonicalize_name(match.group(1))
        assert name not in pins, f"constraints.txt pins {name} twice"
        pins[name] = (match.group(1), match.group(2))
    return pins


def compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


# ------------------------------------------------------------------------ Dockerfile


def test_dockerfile_installs_the_libraries_open3d_needs() -> None:
    # libOpen3D.so links libGL, libEGL, libX11, libusb, libudev, libidn2 (readelf -d)
    assert {"libgl1", "libegl1", "libx11-6", "libusb-1.0-0", "libudev1", "libidn2-0"} <= (
        apt_packages()
    )


def _needed(path: Path) -> list[str]:
    """The DT_NEEDED entries of an ELF64 little-endian shared object ([] if not one)."""
    data = path.read_bytes()
    if data[:4] != b"\x7fELF" or data[4] != 2 or data[5] != 1:
        return []
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum = struct.unpack_from("<HH", data, 0x3A)
    sections = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + i * shentsize)
                for i in range(shnum)]
    names: list[str] = []
    for _, sh_type, _, _, offset, size, link, _, _, _ in sections:
        if sh_type != 6:  # SHT_DYNAMIC
            continue
        strtab_offset = sections[link][4]
        for i in range(0, size, 16):
            tag, value = struct.unpack_from("<qQ", data, offset + i)
            if tag == 0:
                break
            if tag == 1:  # DT_NEEDED
                end = data.index(b"\0", strtab_offset + value)
                names.append(data[strtab_offset + value:end].decode())
    return names


@pytest.mark.skipif(not shutil.which("dpkg"),
                    reason="needs a Debian system (dpkg) to name the packages")
def test_every_system_library_the_runtime_wheels_link_is_installed_by_the_dockerfile() -> None:
    # The installed versions of the image's dependencies (docker/constraints.txt) are read:
    # each shared object they ship, each library it links that no wheel bundles, must come from
    # a Debian package the Dockerfile installs or that every Debian image has.
    files: list[Path] = []
    for name in constraints():
        try:
            dist = metadata.distribution(name)
        except metadata.PackageNotFoundError:
            continue
        files += [Path(dist.locate_file(f)) for f in dist.files or []
                  if re.search(r"\.so(\.|$)", f.name)]
    # open3d's torch/tensorflow ops load only with those frameworks (not installed)
    files = [f for f in files if f.is_file() and not re.match(r"open3d_t\w+_ops\.so", f.name)]
    assert any(f.name.startswith("libOpen3D") for f in files), "open3d not installed here"
    bundled = {f.name for f in files}
    system = {n for f in files for n in _needed(f)} - bundled
    packages: set[str] = set()
    for soname in sorted(system):
        # the package that ships the soname link (dpkg knows /lib and /usr/lib paths apart)
        owners = subprocess.run(["dpkg", "-S", f"*/{soname}"], capture_output=True, text=True)
        found = {line.split(":")[0] for line in owners.stdout.splitlines()
                 if line.rsplit("/", 1)[-1] == soname}
        assert found, f"{soname}: no Debian package here ships it"
        packages |= found
    missing = packages - apt_packages() - DEBIAN_BASE
    assert not missing, (f"the image's wheels link libraries of {sorted(missing)}, which "
                         "docker/Dockerfile does not install")


def test_no_volume_before_the_archive_is_chowned() -> None:
    steps = instructions()
    volumes = [i for i, (k, _) in enumerate(steps) if k == "VOLUME"]
    chowns = [i for i, (k, a) in enumerate(steps)
              if k == "RUN" and ("chown" in a or re.search(r"install -d -o \S+", a))
              and "/archive" in a]
    assert chowns, "the archive folder is never given to the service account"
    # a VOLUME freezes the folder: later changes to it are lost with the classic builder
    assert all(v > max(chowns) for v in volumes)


def test_runs_as_a_non_root_user_with_a_health_check() -> None:
    steps = instructions()
    users = [a for k, a in steps if k == "USER"]
    assert users and users[-1] not in ("root", "0"), "the image runs as root"
    checks = [a for k, a in steps if k == "HEALTHCHECK"]
    assert checks and "/health" in checks[-1]
    cmd = [a for k, a in steps if k == "CMD"][-1]
    assert cmd == '["serve"]', "the health check is the API's: serve is the default command"


def test_the_build_compiles_the_chains_loops_into_a_cache_the_user_owns() -> None:
    # without it every new container (and `docker compose run` of one command) compiled the
    # numba kernels again: ~25 s of CPU before the first frame
    steps = instructions()
    env = " ".join(a for k, a in steps if k == "ENV")
    match = re.search(r"NUMBA_CACHE_DIR=(\S+)", env)
    assert match, "the image sets no numba cache folder"
    cache = match.group(1)
    runs = [(i, a) for i, (k, a) in enumerate(steps) if k == "RUN"]
    owned = rf"install -d -o rasterserver .*{re.escape(cache)}"
    made = [i for i, a in runs if re.search(owned, a)]
    assert made, "the cache folder is not given to the service account"
    user = max(i for i, (k, _a) in enumerate(steps) if k == "USER")
    warm = [(i, a) for i, a in runs if "rasterserver demo" in a]
    assert warm and warm[-1][0] > user, "the loops are compiled as another user than the service's"
    # the warm-up's demo patient goes to a throw-away archive, never into the image's /archive
    assert re.search(r"RASTERSERVER_ARCHIVE=/tmp/\S+ rasterserver demo", warm[-1][1])
    assert "rm -rf /tmp/" in warm[-1][1]


def test_pip_installs_are_pinned_by_the_constraints_file() -> None:
    steps = instructions()
    copied = [a for k, a in steps if k == "COPY" and "docker/constraints.txt" in a]
    assert copied, "docker/constraints.txt is not copied into the image"
    target = shlex.split(copied[0])[-1].removeprefix("./")
    installs = [c for k, a in steps if k == "RUN" for c in re.split(r"&&", a)
                if "pip install" in c]
    assert installs
    for command in installs:
        words = shlex.split(command)
        pinned = any(words[i] in ("-c", "-r", "--constraint", "--requirement")
                     and words[i + 1] == target for i in range(len(words) - 1))
        assert pinned, f"unpinned: {command.strip()}"
        if any(w == "." or w.startswith(".[") for w in words):  # the project: pinned setuptools
            assert "--no-build-isolation" in words


# ------------------------------------------------------------------------ constraints


def test_constraints_pin_every_dependency_within_pyproject() -> None:
    pins = constraints()
    project = tomllib.loads((REPO / "pyproject.toml").read_text())
    optional = project["project"]["optional-dependencies"]
    required = [*project["project"]["dependencies"], *project["build-system"]["requires"],
                *optional["server"], *optional["dask"]]  # the extras the image installs
    for line in required:
        req = Requirement(line)
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is not pinned in docker/constraints.txt"
        version = pins[name][1]
        assert req.specifier.contains(version, prereleases=True), (
            f"constraints.txt pins {name}=={version}, outside pyproject.toml's {req}")


def test_constraints_are_closed_under_the_installed_requirements() -> None:
    # For each pinned package installed here at the pinned version, everything it requires
    # (with its extras as pyproject.toml asks for them) is pinned too: pip cannot pull in an
    # unpinned package. Packages installed here at another version are not judged.
    pins = constraints()
    project = tomllib.loads((REPO / "pyproject.toml").read_text())
    extras: dict[str, set[str]] = {}
    optional = project["project"]["optional-dependencies"]
    for line in [*project["project"]["dependencies"], *optional["server"], *optional["dask"]]:
        req = Requirement(line)
        extras.setdefault(canonicalize_name(req.name), set()).update(req.extras)
    env = default_environment()
    judged = 0
    for name, (_, version) in pins.items():
        try:
            dist = metadata.distribution(name)
        except metadata.PackageNotFoundError:
            continue
        if dist.version != version:
            continue
        judged += 1
        for line in dist.requires or []:
            req = Requirement(line)
            wanted = {""} | extras.get(name, set())
            if req.marker and not any(req.marker.evaluate({**env, "extra": e}) for e in wanted):
                continue
            assert canonicalize_name(req.name) in pins, (
                f"{name} requires {req}, which docker/constraints.txt does not pin")
    if not judged:  # a fresh environment that resolved newer versions of everything
        pytest.skip("no package is installed here at its pinned version: nothing to judge")


# ------------------------------------------------------------------------ compose


def test_compose_runs_the_api_the_catalogue_and_dask() -> None:
    services = compose()["services"]
    assert services["api"]["command"][0] == "serve"
    assert services["db"]["image"].startswith("postgres:")
    assert services["scheduler"]["entrypoint"] == ["dask", "scheduler"]
    assert services["worker"]["entrypoint"] == ["dask", "worker"]
    assert services["worker"]["command"][0] == "tcp://scheduler:8786"


def test_every_service_has_a_health_check_and_a_restart_policy() -> None:
    for name, service in compose()["services"].items():
        if "cli" in service.get("profiles", []):  # one-off commands: `compose run --rm cli`
            assert service.get("restart") == "no", name
            continue
        assert service.get("restart") in ("always", "unless-stopped", "on-failure"), name
        check = service.get("healthcheck") or {}
        assert check.get("test") and not check.get("disable"), f"{name}: no health check"


def test_only_the_api_is_published_and_only_on_the_loopback() -> None:
    document = compose()
    networks = document["networks"]
    for name, service in document["services"].items():
        assert "network_mode" not in service, name
        if name != "api":
            assert "ports" not in service, f"{name} publishes a port"
    for port in document["services"]["api"]["ports"]:
        assert str(port).startswith("127.0.0.1:"), f"the API is published on {port}"
    # The Dask scheduler unpickles what it is sent: only on internal networks, which nothing
    # outside the host reaches and no port can be published from.
    for name in ("scheduler", "worker", "db"):
        for network in document["services"][name]["networks"]:
            assert networks[network].get("internal") is True, f"{name} on {network}"


def test_the_archive_volume_is_mounted_where_the_image_keeps_it() -> None:
    services = compose()["services"]
    # workers read the frames and write the derived files under the root the driver (`cli`)
    # sends them: the same volume at the same path; the catalogue only the driver has
    for name in ("api", "cli", "worker"):
        assert "archive:/archive" in services[name]["volumes"], name
    assert services["cli"]["environment"]["RASTERSERVER_ARCHIVE"] == "/archive"
    assert "RASTERSERVER_DATABASE_URL" not in str(services["worker"])


def test_check_rootfs_script_parses_and_cleans_up() -> None:
    script = DOCKER / "check-rootfs.sh"
    subprocess.run(["bash", "-n", str(script)], check=True)
    text = script.read_text()
    assert "trap cleanup EXIT" in text and "umount" in text
    helper = DOCKER / "rootfs_check.py"
    compile(helper.read_text(), str(helper), "exec")  # no __pycache__ left in docker/


def _flatten(tree: dict, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in tree.items():
        name = f"{prefix}.{key}" if prefix else key
        out.update(_flatten(value, name) if isinstance(value, dict) else {name: value})
    return out


def test_the_image_gives_its_dask_workers_the_settings_of_the_local_cluster() -> None:
    from rasterserver.engines import CLIENT_CONFIG, LOCAL_WORKER_CONFIG

    assert ("COPY", "docker/dask.yaml /etc/dask/rasterserver.yaml") in instructions()
    settings = _flatten(yaml.safe_load((DOCKER / "dask.yaml").read_text()))
    assert settings == {**LOCAL_WORKER_CONFIG, **CLIENT_CONFIG}


def test_the_dask_settings_file_takes_effect_in_a_worker_process(tmp_path: Path) -> None:
    # what a `dask worker` of the image reads: the nanny's environment for the worker and
    # the profiler switch, in a fresh interpreter pointed at the file as /etc/dask would be
    shutil.copy(DOCKER / "dask.yaml", tmp_path / "rasterserver.yaml")
    script = (
        "import dask, distributed; from distributed.nanny import _get_env_variables as e;"
        "print(sorted(e('distributed.nanny.pre-spawn-environ')),"
        " dask.config.get('distributed.worker.profile.enabled'))"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], check=True, capture_output=True, text=True,
        env={**os.environ, "DASK_CONFIG": str(tmp_path)},
    ).stdout.split()
    assert "'MALLOC_TRIM_THRESHOLD_'," not in out and out[-1] == "False"
