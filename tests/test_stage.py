"""The stage protocol: run_stage's checks, parameter validation and hashing, the context."""

from __future__ import annotations

import hashlib
import pickle
from typing import Any, ClassVar

import numpy as np
import pytest
from pydantic import BaseModel, Field, ValidationError

from rasterserver.errors import InputError
from rasterserver.records import Image, Record
from rasterserver.stage import (
    Stage,
    StageContext,
    StageParams,
    coerce_params,
    params_hash,
    run_stage,
    stage_problems,
)


class Mask(Record):
    """A boolean mask, only here to be the wrong record type."""

    kind: ClassVar[str] = "test-stage.mask"
    mask: np.ndarray


class Threshold(Stage[Image, Mask]):
    """Mark the pixels at or above a threshold."""

    name = "test.threshold"
    stage = "mask"
    version = "1"
    input_type = Image
    output_type = Mask

    class Params(StageParams):
        threshold: int = Field(20, ge=0, description="Least grey value marked.")
        gain: float = Field(1.0, gt=0, description="Factor applied before thresholding.")
        label: str = Field("x", description="Free text, to test strings in the hash.")

    def run(self, data: Image, params: Params, context: StageContext) -> Mask:
        return Mask(data.pixels * params.gain >= params.threshold)


class Calibrated(Stage[Image, Image]):
    """Needs a calibration and an extras key; returns the image unchanged."""

    name = "test.calibrated"
    stage = "check"
    version = "1"
    input_type = Image
    output_type = Image
    requires = ("calibration", "station_id")

    def run(self, data: Image, params: StageParams, context: StageContext) -> Image:
        seen.append((context.calibration, context.extras["station_id"]))
        return data


seen: list[tuple[Any, Any]] = []


class Liar(Stage[Image, Mask]):
    """Declares a Mask but returns the image."""

    name = "test.liar"
    stage = "mask"
    version = "1"
    input_type = Image
    output_type = Mask

    def run(self, data: Image, params: StageParams, context: StageContext) -> Mask:
        return data  # type: ignore[return-value]


class Failing(Stage[Image, Image]):
    """Raises from run."""

    name = "test.failing"
    stage = "check"
    version = "3.1"
    input_type = Image
    output_type = Image

    def run(self, data: Image, params: StageParams, context: StageContext) -> Image:
        raise InputError("no raster lines found")


class InPlace(Stage[Image, Image]):
    """Tries to modify its input in place, which records do not allow."""

    name = "test.in-place"
    stage = "check"
    version = "1"
    input_type = Image
    output_type = Image

    def run(self, data: Image, params: StageParams, context: StageContext) -> Image:
        data.pixels[0, 0] = 0
        return data


def _image(seed: int = 3) -> Image:
    rng = np.random.default_rng(seed)
    return Image(rng.integers(0, 40, (6, 8), dtype=np.uint8))


# --- running -------------------------------------------------------------------------------


def test_run_with_default_dict_and_model_params() -> None:
    image = _image()
    by_default = run_stage(Threshold(), image)
    assert isinstance(by_default, Mask)
    np.testing.assert_array_equal(by_default.mask, image.pixels >= 20)
    by_dict = run_stage(Threshold(), image, {"threshold": 30})
    np.testing.assert_array_equal(by_dict.mask, image.pixels >= 30)
    by_model = run_stage(Threshold(), image, Threshold.Params(threshold=30))
    assert by_model == by_dict


def test_run_stage_accepts_the_class() -> None:
    assert run_stage(Threshold, _image()) == run_stage(Threshold(), _image())


def test_wrong_input_type_is_refused_naming_the_plugin() -> None:
    with pytest.raises(InputError, match=r"'test\.threshold' takes Image records .*not Mask"):
        run_stage(Threshold(), Mask(np.zeros(3, dtype=bool)))  # type: ignore[arg-type]


def test_wrong_output_type_is_a_plugin_bug() -> None:
    with pytest.raises(TypeError, match=r"'test\.liar' version 1 returned Image.*output_type Mask"):
        run_stage(Liar(), _image())


def test_errors_from_run_keep_their_type_and_name_the_plugin() -> None:
    with pytest.raises(InputError, match="no raster lines found") as info:
        run_stage(Failing(), _image())
    assert "raised by stage plugin 'test.failing' version 3.1" in info.value.__notes__


def test_a_stage_cannot_modify_its_input_in_place() -> None:
    image = _image()
    before = image.content_hash()
    with pytest.raises(ValueError, match="read-only"):
        run_stage(InPlace(), image)
    assert image.content_hash() == before


# --- parameters ----------------------------------------------------------------------------


def test_unknown_parameter_names_plugin_key_and_known_parameters() -> None:
    with pytest.raises(InputError) as info:
        run_stage(Threshold(), _image(), {"treshold": 5})
    message = str(info.value)
    assert "'test.threshold'" in message
    assert "unknown parameter 'treshold'" in message
    assert "threshold, gain, label" in message


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"threshold": "high"}, "threshold"),
        ({"threshold": -1}, "threshold"),
        ({"gain": 0}, "gain"),
        ({"threshold": 2.5}, "threshold"),
    ],
)
def test_invalid_parameter_values_name_plugin_and_field(params: dict[str, Any], field: str) -> None:
    with pytest.raises(InputError, match=rf"stage plugin 'test\.threshold': {field}: "):
        run_stage(Threshold(), _image(), params)


def test_params_of_another_stage_or_not_a_mapping_are_refused() -> None:
    class OtherParams(BaseModel):
        threshold: int = 1

    with pytest.raises(InputError, match="must be its own Params or a mapping, not"):
        run_stage(Threshold(), _image(), OtherParams())
    with pytest.raises(InputError, match="must be a mapping, not list"):
        run_stage(Threshold(), _image(), [("threshold", 1)])  # type: ignore[arg-type]


def test_coerce_params_returns_the_stages_model() -> None:
    params = coerce_params(Threshold(), {"gain": 2})
    assert isinstance(params, Threshold.Params)
    assert params.gain == 2.0
    assert coerce_params(Threshold(), params) is params


def test_params_are_frozen_and_hashable() -> None:
    params = Threshold.Params()
    with pytest.raises(ValidationError, match="frozen"):
        params.threshold = 3  # type: ignore[misc]
    assert hash(params) == hash(Threshold.Params())


def test_params_hash_is_canonical_json() -> None:
    # Pinned: sorted keys, no spaces, defaults included. Provenance keys depend on it.
    expected = hashlib.sha256(b'{"gain":1.5,"label":"x","threshold":20}').hexdigest()
    assert params_hash(Threshold.Params(gain=1.5)) == expected


def test_params_hash_same_params_same_hash() -> None:
    base = params_hash(Threshold.Params())
    assert params_hash(Threshold.Params()) == base
    assert params_hash(coerce_params(Threshold(), {})) == base
    assert params_hash(coerce_params(Threshold(), {"threshold": 20})) == base  # explicit default
    assert params_hash(coerce_params(Threshold(), {"gain": 1})) == base  # 1 is coerced to 1.0


def test_an_option_added_switched_off_keeps_the_digest() -> None:
    """A field named in ``digest_omits_defaults`` is left out of the digest while at its
    default: the parameters hash as before the option was added (stored results keep
    their identity), and differently once it is set."""

    class Before(StageParams):
        threshold: int = 20

    class After(StageParams):
        digest_omits_defaults: ClassVar[frozenset[str]] = frozenset({"bend"})
        threshold: int = 20
        bend: float = 0.0

    assert params_hash(After()) == params_hash(Before())
    assert params_hash(After(bend=0.0)) == params_hash(Before())
    assert params_hash(After(bend=0.8)) != params_hash(Before())
    assert params_hash(After(threshold=5)) == params_hash(Before(threshold=5))
    assert "digest_omits_defaults" not in After.model_fields


def test_the_numbering_options_tried_as_versions_26_to_28_keep_the_digest() -> None:
    """Pinned: the digest of the line numbering's version 30 defaults. The options tried as
    versions 26-28 (``end_jump``, ``final_run``, ``course_beyond``, ``block_gain_share``,
    ``block_one_shift``), off, are left out of it at their defaults, as they were of
    version 25's when they were added (version 25's parameters, with ``one_sided_peaks`` 5
    and the two steps of version 29 off, give another digest, as do version 29's, with
    ``bracket_line`` off); switched on, they change it."""
    from rasterserver_plugins.numbering_params import CodeWindowParams

    v30 = "309efe99739c771e6351fe3db1257ffc382bf78c03b0ce1ff8b0f67ab5d0cc80"
    assert params_hash(CodeWindowParams()) == v30
    v25 = CodeWindowParams(meet_tolerance=0.0, outer_gap=0.0, one_sided_peaks=5)
    assert params_hash(v25) != v30
    assert params_hash(CodeWindowParams(bracket_line=False)) != v30
    # the ambiguous-gap option (``gap_peaks``), off, added after version 30: switched on, it
    # changes the digest
    assert params_hash(CodeWindowParams(gap_peaks=20)) != v30
    assert params_hash(CodeWindowParams(gap_departure=0.3)) != v30
    assert params_hash(CodeWindowParams(end_jump=2.8)) != v30
    assert params_hash(CodeWindowParams(block_gain_share=0.4, block_one_shift=True)) != v30


def test_params_hash_key_order_is_irrelevant() -> None:
    a = coerce_params(Threshold(), {"threshold": 5, "gain": 2.0, "label": "y"})
    b = coerce_params(Threshold(), {"label": "y", "gain": 2.0, "threshold": 5})
    assert params_hash(a) == params_hash(b)


def test_params_hash_differs_for_different_params() -> None:
    hashes = {
        params_hash(coerce_params(Threshold(), p))
        for p in ({}, {"threshold": 21}, {"gain": 1.0000001}, {"label": "X"}, {"label": "ü"})
    }
    assert len(hashes) == 5


# --- context -------------------------------------------------------------------------------


def test_required_context_is_checked() -> None:
    with pytest.raises(InputError, match=r"'test\.calibrated' needs calibration, station_id"):
        run_stage(Calibrated(), _image())
    with pytest.raises(InputError, match="needs station_id"):
        run_stage(Calibrated(), _image(), context=StageContext(calibration={"f": 1.0}))
    seen.clear()
    context = StageContext(calibration={"f": 1.0}, extras={"station_id": "S1"})
    run_stage(Calibrated(), _image(), context=context)
    assert seen == [({"f": 1.0}, "S1")]


def test_context_is_read_only_and_pickles() -> None:
    extras = {"station_id": "S1"}
    context = StageContext(raster=("L", "H", "L"), extras=extras)
    extras["station_id"] = "changed"  # the context took a copy
    assert context.extras["station_id"] == "S1"
    with pytest.raises(TypeError):
        context.extras["x"] = 1  # type: ignore[index]
    with pytest.raises(AttributeError):
        context.raster = None  # type: ignore[misc]
    back = pickle.loads(pickle.dumps(context))
    assert back.raster == ("L", "H", "L")
    assert dict(back.extras) == {"station_id": "S1"}
    assert context.has("raster") and not context.has("calibration")


def test_stage_and_params_pickle_for_dask_workers() -> None:
    stage = pickle.loads(pickle.dumps(Threshold()))
    params = pickle.loads(pickle.dumps(Threshold.Params(threshold=7)))
    assert params == Threshold.Params(threshold=7)
    assert run_stage(stage, _image(), params) == run_stage(Threshold(), _image(), {"threshold": 7})


# --- declarations --------------------------------------------------------------------------


def test_valid_stages_have_no_problems() -> None:
    for stage in (Threshold, Threshold(), Calibrated, Liar, Failing):
        assert stage_problems(stage) == []
    assert repr(Threshold()) == "<Threshold test.threshold version 1>"


def test_stage_problems_lists_every_problem() -> None:
    class Incomplete(Stage[Image, Image]):
        name = "Bad Name"
        version = ""
        input_type = Image
        output_type = dict  # type: ignore[assignment]

        class Params(BaseModel):
            threshold: int

    problems = "\n".join(stage_problems(Incomplete))
    assert "abstract method(s) not implemented: run" in problems
    assert "name must be a lowercase string" in problems
    assert "stage must be a lowercase stage kind" in problems
    assert "version must be a non-empty string" in problems
    assert "output_type must be a Record subclass" in problems
    assert "Params must be frozen" in problems
    assert "Params must forbid unknown keys" in problems
    assert "Params fields without a default: threshold" in problems
    assert stage_problems(object()) == [
        "builtins.object is not a subclass of rasterserver.stage.Stage"
    ]


def test_run_stage_refuses_an_invalid_stage() -> None:
    class NoVersion(Stage[Image, Image]):
        """Forgot its version."""

        name = "test.no-version"
        stage = "check"
        input_type = Image
        output_type = Image

        def run(self, data: Image, params: StageParams, context: StageContext) -> Image:
            return data

    with pytest.raises(TypeError, match=r"'test\.no-version' is not a valid stage plugin: version"):
        run_stage(NoVersion(), _image())
