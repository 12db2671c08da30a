"""Plugin discovery through real ``importlib.metadata`` entry points of fake distributions.

Each test writes a distribution into ``tmp_path`` (modules plus a ``*.dist-info`` folder with
``METADATA`` and ``entry_points.txt``) and puts it on ``sys.path``: exactly what ``pip install``
of a third-party plugin package leaves behind.
"""

from __future__ import annotations

import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from rasterserver.errors import InputError, NotFoundError
from rasterserver.records import Image
from rasterserver.registry import STAGE_GROUP, Registry, get_registry
from rasterserver.stage import run_stage

INVERT_MODULE = '''
"""A third-party stage package, written as a plugin author would."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from rasterserver.records import Image
from rasterserver.stage import Stage, StageContext, StageParams


class InvertImage(Stage[Image, Image]):
    """Invert grey values relative to a white level."""

    name = "thirdparty.invert"
    stage = "invert"
    version = "1.0"
    input_type = Image
    output_type = Image

    class Params(StageParams):
        white: int | None = Field(None, ge=1, description="White level; dtype maximum if None.")
        role: str = Field("inverted", description="Role of the output image.")

    def run(self, data: Image, params: Params, context: StageContext) -> Image:
        dtype = data.pixels.dtype
        white = np.iinfo(dtype).max if params.white is None else params.white
        return Image((white - np.minimum(data.pixels, white)).astype(dtype), role=params.role)


class NoDefaults(InvertImage):
    """Invalid: a parameter without a default."""

    name = "thirdparty.no-defaults"

    class Params(StageParams):
        white: int


class Renamed(InvertImage):
    """Registered under another name than its own."""

    name = "thirdparty.renamed"


NOT_A_STAGE = "just a string"
'''

BROKEN_MODULE = """
raise ImportError("needs libfoo, which is not installed")
"""

MODULES = ("thirdparty_plugin", "thirdparty_broken", "otherparty_plugin")


def write_distribution(
    root: Path, name: str, version: str, entry_points: dict[str, str], modules: dict[str, str]
) -> None:
    """Write modules and a ``<name>-<version>.dist-info`` into ``root``, as pip would."""
    for module, source in modules.items():
        (root / f"{module}.py").write_text(textwrap.dedent(source), encoding="utf-8")
    info = root / f"{name.replace('-', '_')}-{version}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(
        f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n", encoding="utf-8"
    )
    lines = [f"[{STAGE_GROUP}]", *(f"{ep} = {value}" for ep, value in entry_points.items())]
    (info / "entry_points.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")


@pytest.fixture
def clean_modules() -> Iterator[None]:
    """Forget the fake plugin modules, so each test imports its own ``tmp_path`` copy."""
    for module in MODULES:
        sys.modules.pop(module, None)
    yield
    for module in MODULES:
        sys.modules.pop(module, None)


@pytest.fixture
def thirdparty(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, clean_modules: None) -> Path:
    """Install ``thirdparty-plugin 1.0``: one good stage and several broken entry points."""
    write_distribution(
        tmp_path,
        "thirdparty-plugin",
        "1.0",
        {
            "thirdparty.invert": "thirdparty_plugin:InvertImage",
            "thirdparty.needs-libfoo": "thirdparty_broken:Stage",
            "thirdparty.not-a-stage": "thirdparty_plugin:NOT_A_STAGE",
            "thirdparty.no-defaults": "thirdparty_plugin:NoDefaults",
            "thirdparty.other-name": "thirdparty_plugin:Renamed",
            "thirdparty.missing-attr": "thirdparty_plugin:DoesNotExist",
        },
        {"thirdparty_plugin": INVERT_MODULE, "thirdparty_broken": BROKEN_MODULE},
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def _image(seed: int = 11) -> Image:
    rng = np.random.default_rng(seed)
    return Image(rng.integers(0, 256, (5, 7), dtype=np.uint8))


def test_third_party_plugin_is_discovered_with_its_package(thirdparty: Path) -> None:
    registry = Registry().discover()
    assert "thirdparty.invert" in registry.names()
    info = registry.info("thirdparty.invert")
    assert info.ok
    assert (info.stage, info.version, info.input_kind, info.output_kind) == (
        "invert",
        "1.0",
        "image",
        "image",
    )
    assert (info.package, info.package_version) == ("thirdparty-plugin", "1.0")
    assert info.entry_point == "thirdparty_plugin:InvertImage"
    assert info.summary == "Invert grey values relative to a white level."
    assert info.error is None


def test_third_party_plugin_runs_through_run_stage(thirdparty: Path) -> None:
    stage = Registry().discover().get("thirdparty.invert")
    image = _image()
    inverted = run_stage(stage, image)
    np.testing.assert_array_equal(inverted.pixels, 255 - image.pixels)
    assert inverted.role == "inverted"
    clipped = run_stage(stage, image, {"white": 100, "role": "test"})
    np.testing.assert_array_equal(clipped.pixels, 100 - np.minimum(image.pixels, 100))
    with pytest.raises(InputError, match=r"'thirdparty\.invert': unknown parameter 'black'"):
        run_stage(stage, image, {"black": 1})


def test_get_imports_only_the_named_plugin(thirdparty: Path) -> None:
    registry = Registry().discover()
    registry.get("thirdparty.invert")
    assert "thirdparty_broken" not in sys.modules


@pytest.mark.parametrize(
    ("name", "reason"),
    [
        ("thirdparty.needs-libfoo", "import failed: ImportError: needs libfoo, which is not"),
        ("thirdparty.not-a-stage", "thirdparty_plugin:NOT_A_STAGE is 'str', not a rasterserver"),
        ("thirdparty.no-defaults", "Params fields without a default: white"),
        ("thirdparty.other-name", "differs from the stage's name 'thirdparty.renamed'"),
        ("thirdparty.missing-attr", "import failed: AttributeError"),
    ],
)
def test_broken_plugins_are_listed_with_the_reason(
    thirdparty: Path, name: str, reason: str
) -> None:
    registry = Registry().discover()
    info = registry.info(name)
    assert info.status == "broken"
    assert reason in (info.error or "")
    assert (info.package, info.package_version) == ("thirdparty-plugin", "1.0")
    with pytest.raises(NotFoundError, match="is broken: ") as raised:
        registry.get(name)
    assert reason in str(raised.value)
    # The good plugin of the same package is unaffected.
    assert registry.info("thirdparty.invert").ok
    assert run_stage(registry.get("thirdparty.invert"), _image()).role == "inverted"


def test_infos_lists_good_and_broken_plugins(thirdparty: Path) -> None:
    infos = {info.name: info for info in Registry().discover().infos()}
    assert infos["thirdparty.invert"].ok
    broken = {name for name, info in infos.items() if not info.ok}
    assert {"thirdparty.needs-libfoo", "thirdparty.not-a-stage", "thirdparty.no-defaults"} <= broken
    # Broken plugins of unknown kind come after every loadable one.
    ordered = Registry().discover().infos()
    kinds = [info.stage is None for info in ordered]
    assert kinds == sorted(kinds)


def test_unknown_name_lists_available_plugins(thirdparty: Path) -> None:
    registry = Registry().discover()
    with pytest.raises(NotFoundError) as raised:
        registry.get("thirdparty.invrt")
    message = str(raised.value)
    assert "no stage plugin named 'thirdparty.invrt'" in message
    assert "available: " in message and "thirdparty.invert" in message
    assert "broken: " in message and "thirdparty.needs-libfoo" in message
    with pytest.raises(NotFoundError, match="no stage plugin named"):
        registry.info("thirdparty.invrt")


def test_for_stage_and_stage_kinds(thirdparty: Path) -> None:
    registry = Registry().discover()
    assert [stage.name for stage in registry.for_stage("invert")] == ["thirdparty.invert"]
    assert registry.for_stage("no-such-kind") == []
    assert "invert" in registry.stage_kinds()
    assert [info.name for info in registry.infos("invert")] == ["thirdparty.invert"]


def _install_otherparty(root: Path, names: dict[str, str]) -> None:
    source = "from thirdparty_plugin import InvertImage\n\n" + "\n".join(
        f"class {cls}(InvertImage):\n    '''Another inverter.'''\n    name = {name!r}\n"
        for name, cls in names.items()
    )
    write_distribution(
        root,
        "otherparty",
        "2.5",
        {name: f"otherparty_plugin:{cls}" for name, cls in names.items()},
        {"otherparty_plugin": source},
    )


def test_default_for_is_deterministic_and_configurable(
    thirdparty: Path, tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    other = tmp_path_factory.mktemp("otherparty")
    _install_otherparty(other, {"a.invert": "AInvert", "z.invert": "ZInvert"})
    monkeypatch.syspath_prepend(str(other))

    registry = Registry().discover()
    assert [stage.name for stage in registry.for_stage("invert")] == [
        "a.invert",
        "thirdparty.invert",
        "z.invert",
    ]
    assert registry.default_for("invert").name == "a.invert"  # first by name
    # The built-in distribution wins a tie, so installing a package cannot change a default.
    preferring = Registry(builtin_distribution="ThirdParty_Plugin").discover()
    assert preferring.default_for("invert").name == "thirdparty.invert"
    configured = Registry(defaults={"invert": "z.invert"}).discover()
    assert configured.default_for("invert").name == "z.invert"
    # The found default is kept, but a default configured later still wins, and forgetting it
    # finds the first by name again.
    assert registry.default_for("invert").name == "a.invert"
    registry.defaults["invert"] = "z.invert"
    assert registry.default_for("invert").name == "z.invert"
    del registry.defaults["invert"]
    assert registry.default_for("invert").name == "a.invert"

    with pytest.raises(NotFoundError, match=r"no working stage plugin implements stage 'peakz'"):
        registry.default_for("peakz")
    with pytest.raises(InputError, match=r"configured as 'thirdparty\.invert', which implements"):
        Registry(defaults={"peaks": "thirdparty.invert"}).discover().default_for("peaks")
    with pytest.raises(NotFoundError, match="is broken"):
        Registry(defaults={"invert": "thirdparty.no-defaults"}).discover().default_for("invert")


def test_a_name_claimed_by_two_packages_is_broken_in_both(
    thirdparty: Path, tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    other = tmp_path_factory.mktemp("otherparty")
    _install_otherparty(other, {"thirdparty.invert": "Impostor"})
    monkeypatch.syspath_prepend(str(other))

    registry = Registry().discover()
    claims = [info for info in registry.infos() if info.name == "thirdparty.invert"]
    assert {info.package for info in claims} == {"thirdparty-plugin", "otherparty"}
    assert all(info.status == "broken" for info in claims)
    assert all("registered more than once" in (info.error or "") for info in claims)
    with pytest.raises(NotFoundError, match="registered more than once"):
        registry.get("thirdparty.invert")


def test_an_instance_may_be_registered(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, clean_modules: None
) -> None:
    write_distribution(
        tmp_path,
        "thirdparty-plugin",
        "1.1",
        {"thirdparty.invert": "thirdparty_plugin:INSTANCE"},
        {"thirdparty_plugin": INVERT_MODULE + "\nINSTANCE = InvertImage()\n"},
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = Registry().discover()
    stage = registry.get("thirdparty.invert")
    assert stage is sys.modules["thirdparty_plugin"].INSTANCE
    assert registry.info("thirdparty.invert").package_version == "1.1"


def test_shared_registry_caches_until_discover(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, clean_modules: None
) -> None:
    shared = get_registry().discover()
    assert get_registry() is shared
    assert "thirdparty.invert" not in shared.names()

    write_distribution(
        tmp_path,
        "thirdparty-plugin",
        "1.0",
        {"thirdparty.invert": "thirdparty_plugin:InvertImage"},
        {"thirdparty_plugin": INVERT_MODULE},
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "thirdparty.invert" not in shared.names()  # cached per process
    assert "thirdparty.invert" in shared.discover().names()
    assert shared.get("thirdparty.invert").stage == "invert"

    monkeypatch.undo()  # take the distribution off sys.path again
    assert "thirdparty.invert" not in get_registry().discover().names()


def test_broken_plugins_are_logged_unless_reported_by_the_caller(
    thirdparty: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level("WARNING", logger="rasterserver.registry"):
        Registry().discover().info("thirdparty.needs-libfoo")
    assert "stage plugin thirdparty.needs-libfoo" in caplog.text
    assert "needs libfoo" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="rasterserver.registry"):
        Registry(warn_broken=False).discover().infos()
    assert caplog.text == ""


def test_record_kinds_are_known_in_a_fresh_process_without_imports() -> None:
    # A fresh `rasterserver verify` reads stored results of every kind before any stage has
    # run in it; the installed plugins must decide which record kinds exist, not import order.
    import subprocess

    code = textwrap.dedent(
        """
        import sys
        from rasterserver.registry import Registry
        assert "rasterserver.records_lines" not in sys.modules
        registry = Registry()
        for kind in ("image", "peaks", "lines", "ordered-lines", "numbered-lines", "points",
                     "surface", "mesh", "backshape"):
            print(kind, registry.record_type(kind).__name__)
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr
    kinds = dict(line.split() for line in done.stdout.splitlines())
    assert kinds["peaks"] == "Peaks"
    assert kinds["numbered-lines"] == "NumberedLines"
    assert kinds["backshape"] == "BackShape"


def test_unknown_record_kind_is_not_found(thirdparty: Path) -> None:
    with pytest.raises(NotFoundError, match="no installed stage plugin"):
        Registry().record_type("no-such-kind")


def test_listing_the_stages_does_not_load_the_mesh_library_or_scipy_signal() -> None:
    # Every command that discovers the stages imports their modules; open3d (~0.6 s) and
    # scipy.signal (~0.7 s) are loaded where a stage runs, not when it is listed.
    import subprocess

    code = textwrap.dedent(
        """
        import sys
        from rasterserver.cli import main
        assert main(["plugins"]) == 0
        print(" ".join(m for m in ("open3d", "scipy.signal") if m in sys.modules))
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr
    assert "lines.hierarchical" in done.stdout
    assert done.stdout.splitlines()[-1] == "", done.stdout.splitlines()[-1]
