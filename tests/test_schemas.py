"""The declared record schemas (nimbus.schemas): every record kind read back refuses each malformed case with one
message naming the file, the line (a store) and the field; a store still reads its good lines around a bad one;
and what the project's own writers write fits."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest

from benchmark.store import MAX_WARNED_LINES, ResultsStore, load_results
from nimbus.errors import NimbusError, SkippedRecordWarning
from nimbus.schemas import (ResultRecord, RunConfig, SceneManifest, SettingManifest, TransformsFile, TransformsFrame,
                            problem, read_json_file)

ROOT = Path(__file__).resolve().parents[1]
DEEP = "[" * 200_000 + "]" * 200_000  # json.loads recurses once per level: a RecursionError, not a ValueError
GOOD = {"cell_id": "garden-tiny_H_3dgs_tiny_s0", "scene": "garden", "size": "tiny", "weather": "H", "method": "3dgs",
        "preset": "tiny", "seed": 0, "status": "ok", "psnr": 20.0, "ssim": 0.5, "lpips": 0.3,
        "per_view": [{"name": "000.png", "psnr": 20.0, "ssim": 0.5, "lpips": 0.3}]}


def _line(text: str | dict) -> str:
    return text if isinstance(text, str) else json.dumps(text)  # NaN is written as the token NaN


# case -> (the bad line of results.jsonl, the problem the warning names)
STORE_CASES = {
    "list-as-cell_id": (dict(GOOD, cell_id=["a", "b"]), "field 'cell_id' must be a string, got ['a', 'b']"),
    "string-as-psnr": (dict(GOOD, psnr="abc"), "field 'psnr' must be a number or null, got 'abc'"),
    "missing-scene": ({k: v for k, v in GOOD.items() if k != "scene"}, "field 'scene' is missing"),
    "nested-200k-deep": (DEEP, "is not valid JSON (nested too deeply)"),
    "deep-inside-a-field": ('{"cell_id": "x", "psnr": ' + DEEP + "}", "is not valid JSON (nested too deeply)"),
    "list-line": ("[1, 2]", "holds a list, not an object"),
    "number-line": ("7", "holds an integer, not an object"),
    "null-line": ("null", "holds null, not an object"),
    "nan-psnr": (dict(GOOD, psnr=float("nan")), "field 'psnr' must be a finite number, got nan"),
    "infinite-ssim": (dict(GOOD, ssim=float("inf")), "field 'ssim' must be a finite number, got inf"),
    "unknown-status": (dict(GOOD, status="done"), "field 'status' must be 'ok' or 'error', got 'done'"),
    "bool-as-seed": (dict(GOOD, seed=True), "field 'seed' must be an integer, got True"),
    "negative-seed": (dict(GOOD, seed=-3), "field 'seed' must be >= 0, got -3"),
    "empty-method": (dict(GOOD, method=""), "field 'method' must not be empty"),
    "string-per-view-psnr": (dict(GOOD, per_view=[{"name": "000.png", "psnr": "x"}]),
                             "field 'per_view[0].psnr' must be a number or null, got 'x'"),
    "per-view-not-a-list": (dict(GOOD, per_view={"000.png": 20.0}), "field 'per_view' must be a list"),
    "number-as-override": (dict(GOOD, overrides={"iterations": 5}), "field 'overrides.iterations' must be a string"),
    "number-as-scene_path": (dict(GOOD, scene_path=5), "field 'scene_path' must be a string or null, got 5"),
    "not-json": ("{'cell_id': 'a'}", "is not valid JSON"),
    "not-utf8": ('{"cell_id": "\udcff"}', "is not valid JSON (not UTF-8 text)"),
}


def _store_with(tmp_path: Path, bad: str | dict) -> Path:
    """A store of a good record, the bad line (line 2), and another good record."""
    lines = [json.dumps(GOOD), _line(bad), json.dumps(dict(GOOD, cell_id="street-tiny_H_3dgs_tiny_s0", scene="street"))]
    data = "".join(line + "\n" for line in lines).encode("utf-8", "surrogateescape")
    (tmp_path / "results.jsonl").write_bytes(data)
    return tmp_path


@pytest.mark.parametrize("case", list(STORE_CASES))
def test_a_bad_store_line_is_skipped_naming_line_and_field_and_the_rest_reads(case, tmp_path):
    bad, words = STORE_CASES[case]
    root = _store_with(tmp_path, bad)
    with pytest.warns(SkippedRecordWarning) as caught:
        df = load_results(root)
    messages = [str(w.message) for w in caught if issubclass(w.category, SkippedRecordWarning)]
    assert len(messages) == 1, messages
    assert messages[0].startswith(f"{root / 'results.jsonl'} line 2: {words}"), messages[0]
    assert "\n" not in messages[0] and len(messages[0]) < 400
    assert sorted(df["cell_id"]) == ["garden-tiny_H_3dgs_tiny_s0", "street-tiny_H_3dgs_tiny_s0"]


def test_every_bad_line_is_named_up_to_a_limit_then_counted(tmp_path):
    n_bad = MAX_WARNED_LINES + 5
    lines = [json.dumps(GOOD)] + [json.dumps(dict(GOOD, psnr="abc"))] * n_bad
    (tmp_path / "results.jsonl").write_text("".join(line + "\n" for line in lines))
    with pytest.warns(SkippedRecordWarning) as caught:
        assert [r["cell_id"] for r in ResultsStore(tmp_path).records()] == [GOOD["cell_id"]]
    messages = [str(w.message) for w in caught]
    assert [m.split(":")[0].rsplit(" ", 1)[-1] for m in messages[:MAX_WARNED_LINES]] == \
        [str(i) for i in range(2, 2 + MAX_WARNED_LINES)]
    assert len(messages) == MAX_WARNED_LINES + 1 and "skipped 5 more records" in messages[-1]


def test_unknown_fields_are_allowed_and_the_new_optional_ones_typed():
    assert problem(ResultRecord, dict(GOOD, something_new={"any": [1, "thing"]}, tag=3)) is None
    assert problem(ResultRecord, dict(GOOD, scene_path="/data/garden", scene_hash="ab" * 32)) is None
    assert problem(ResultRecord, dict(GOOD, scene_hash=["ab"])) == "field 'scene_hash' must be a string or null, " \
                                                                   "got ['ab']"
    assert problem(ResultRecord, {k: GOOD[k] for k in ResultRecord.model_json_schema()["required"]}) is None


def test_a_cell_id_that_is_a_path_is_still_refused_not_skipped(tmp_path):
    """The schema takes any string; the confinement check after it (single_name) refuses a path outright."""
    (tmp_path / "results.jsonl").write_text(json.dumps(dict(GOOD, cell_id="x/../../escaped")) + "\n")
    with pytest.raises(NimbusError, match="line 1: 'cell_id'.*not a single file name"):
        ResultsStore(tmp_path).records()


def test_append_refuses_a_record_no_reader_would_read(tmp_path):
    store = ResultsStore(tmp_path)
    for bad, words in [(dict(GOOD, psnr="abc"), "field 'psnr'"), ({"cell_id": "a", "status": "ok"}, "field 'scene'"),
                       (dict(GOOD, status="trained"), "field 'status'")]:
        with pytest.raises(ValueError, match=words):
            store.append(bad)
    assert not store.path.exists()


# --- what the writers write fits ----------------------------------------------------------------------------
@pytest.mark.parametrize("store", sorted(p.parent.name for p in (ROOT / "tables").glob("*/results.jsonl")
                                         if "cell_id" in p.read_text()[:2000]))
def test_the_committed_stores_records_fit(store):
    """Records nimbus-bench run wrote (the committed tables' stores): every line fits, none is skipped."""
    path = ROOT / "tables" / store / "results.jsonl"
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    assert lines and [problem(ResultRecord, json.loads(line)) for line in lines] == [None] * len(lines)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SkippedRecordWarning)
        assert len(ResultsStore(path.parent).records()) == len(lines)


def test_an_error_record_fits():
    from benchmark.cell import Cell, error_record

    rec = error_record(Cell("garden", "H+R", "nimbus", "fast", 3, "small", (("iterations", "10"),)), "boom")
    assert problem(ResultRecord, json.loads(json.dumps(rec))) is None


def test_a_runs_config_json_fits(make_scene, tmp_path):
    from nimbus.methods.registry import get_method
    from nimbus.train.run_folder import read_run_config
    from nimbus.train.runner import Runner

    runner = Runner("3dgs", make_scene(n_views=3), get_method("3dgs").preset("tiny"), tmp_path / "run", seed=7,
                    scene_path="builtin:garden:tiny", progress=False)
    runner.write_config()
    saved = read_run_config(tmp_path / "run")
    assert saved["seed"] == 7 and saved["method"] == "3dgs" and saved["scene_load_args"] == {}


def test_a_builtin_scene_manifest_fits():
    from nimbus.data.builtin import manifest

    assert problem(SceneManifest, json.loads(json.dumps(manifest("garden", "tiny", 3, 8)))) is None


def test_a_written_transforms_json_fits(make_scene, tmp_path):
    from nimbus.data.transforms import write_transforms

    tmp_path.mkdir(exist_ok=True)
    write_transforms(make_scene(n_views=3), tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert problem(TransformsFile, meta) is None
    assert [problem(TransformsFrame, f) for f in meta["frames"]] == [None] * 3


# --- config.json, manifests: one file is the input, so a mismatch is an error naming file and field ----------
CONFIG = {"method": "3dgs", "scene": "builtin:garden:tiny", "seed": 0, "config": {"iterations": 10},
          "scene_load_args": {}}
CONFIG_CASES = {
    "list-as-method": (dict(CONFIG, method=["3dgs"]), "field 'method' must be a string, got ['3dgs']"),
    "string-as-seed": (dict(CONFIG, seed="0"), "field 'seed' must be an integer, got '0'"),
    "missing-scene": ({k: v for k, v in CONFIG.items() if k != "scene"}, "field 'scene' is missing"),
    "nested-200k-deep": (DEEP, "is not valid JSON (nested too deeply)"),
    "non-object": ('["3dgs"]', "holds a list, not an object"),
    "nan-seed": (dict(CONFIG, seed=float("nan")), "field 'seed' must be an integer, got nan"),
    "unknown-load-arg": (dict(CONFIG, scene_load_args={"shell": "rm -rf /"}),
                         "field 'scene_load_args.shell' is not a known key"),
    "list-as-config": (dict(CONFIG, config=[1]), "field 'config' must be an object, got [1]"),
    "huge-seed": (dict(CONFIG, seed=2**40), "field 'seed' must be <= 4294967295"),
}


@pytest.mark.parametrize("case", list(CONFIG_CASES))
def test_a_bad_config_json_is_one_error_naming_file_and_field(case, tmp_path):
    from nimbus.train.run_folder import read_run_config

    bad, words = CONFIG_CASES[case]
    (tmp_path / "config.json").write_text(_line(bad))
    with pytest.raises(NimbusError) as e:
        read_run_config(tmp_path)
    assert str(e.value).startswith(f"{tmp_path / 'config.json'}: {words}") or \
        str(e.value).startswith(f"{tmp_path / 'config.json'} {words}"), str(e.value)
    assert "nimbus-train" in str(e.value) and "\n" not in str(e.value)


VIEW = {"name": "000.png", "image": "images/000.png", "clean": "clean/000.png", "layers": "layers/000.npz",
        "split": "test"}
SETTING = {"setting": "H", "protocol": "onerestore", "seed": 0, "scene": {}, "views": [VIEW]}
SETTING_CASES = {
    "list-as-view-name": (dict(SETTING, views=[dict(VIEW, name=["a"])]), "field 'views[0].name' must be a string"),
    "string-as-seed": (dict(SETTING, seed="0"), "field 'seed' must be an integer or null, got '0'"),
    "missing-views": ({k: v for k, v in SETTING.items() if k != "views"}, "field 'views' is missing"),
    "missing-clean": (dict(SETTING, views=[{"name": "a", "image": "images/a.png"}]),
                      "field 'views[0].clean' is missing"),
    "nested-200k-deep": (DEEP, "is not valid JSON (nested too deeply)"),
    "non-object": ("3", "holds an integer, not an object"),
    "nan-seed": (dict(SETTING, seed=float("nan")), "field 'seed' must be an integer or null, got nan"),
    "unknown-split": (dict(SETTING, views=[dict(VIEW, split="val")]),
                      "field 'views[0].split' must be 'train' or 'test', got 'val'"),
}


@pytest.mark.parametrize("case", list(SETTING_CASES))
def test_a_bad_setting_manifest_is_one_error_naming_file_and_field(case, tmp_path):
    from weather_synth.dataset import read_setting_manifest

    bad, words = SETTING_CASES[case]
    (tmp_path / "manifest.json").write_text(_line(bad))
    with pytest.raises(NimbusError) as e:
        read_setting_manifest(tmp_path)
    assert words in str(e.value) and str(e.value).startswith(str(tmp_path / "manifest.json")), str(e.value)
    assert "nimbus-synth degrade" in str(e.value)


def test_a_good_setting_manifest_reads_with_its_extra_fields(tmp_path):
    from weather_synth.dataset import read_setting_manifest

    (tmp_path / "manifest.json").write_text(json.dumps(dict(SETTING, summary={"views": 1}, extra=[1])))
    assert read_setting_manifest(tmp_path)["extra"] == [1]


@pytest.mark.parametrize("bad, words", [({"seed": "1"}, "field 'seed' must be an integer, got '1'"),
                                        ({"scene": "garden"}, "field 'seed' is missing"),
                                        ({"seed": float("nan")}, "field 'seed' must be an integer, got nan")])
def test_a_bad_scene_manifest_is_one_error(bad, words, tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps(bad))
    with pytest.raises(NimbusError, match="manifest.json: " + words.replace("(", r"\(")):
        read_json_file(tmp_path / "manifest.json", SceneManifest, "render it again")


# transforms.json at the schema level (tests/test_hostile_data.py reads whole scenes)
FRAME = {"file_path": "images/0.png", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}


@pytest.mark.parametrize("schema, value, words", [
    (TransformsFrame, dict(FRAME, file_path=["a.png"]), "field 'file_path' must be a string, got ['a.png']"),
    (TransformsFrame, dict(FRAME, transform_matrix=[[1, 0, 0, "0"]] * 4),
     "field 'transform_matrix[0][3]' must be a number, got '0'"),
    (TransformsFrame, {"file_path": "a.png"}, "field 'transform_matrix' is missing"),
    (TransformsFrame, dict(FRAME, fl_x=float("nan")), "field 'fl_x' must be a finite number, got nan"),
    (TransformsFrame, dict(FRAME, transform_matrix=[[1, 0, 0, 0]] * 2),
     "field 'transform_matrix' must have at least 3 entries, got 2"),
    (TransformsFrame, [FRAME], "holds a list, not an object"),
    (TransformsFile, {"frames": []}, "field 'frames' must not be empty"),
    (TransformsFile, {"frames": [FRAME], "test_filenames": "0.png"}, "field 'test_filenames' must be a list"),
    (TransformsFile, {"w": "640", "frames": [FRAME]}, "field 'w' must be a number or null, got '640'"),
])
def test_transforms_schema_names_the_field(schema, value, words):
    assert problem(schema, value) == words or problem(schema, value).startswith(words)


def test_the_scene_load_args_schema_is_the_readers_list():
    import inspect

    from nimbus.schemas import SceneLoadArgs
    from nimbus.train.run_folder import SCENE_LOAD_ARGS, load_scene_arg

    assert set(SceneLoadArgs.model_fields) == set(SCENE_LOAD_ARGS)
    assert set(SCENE_LOAD_ARGS) <= set(inspect.signature(load_scene_arg).parameters)


def test_the_schemas_export_as_json_schema():
    """What the docs describe: each kind is a JSON Schema with its required fields."""
    required = {kind: set(kind.model_json_schema().get("required", [])) for kind in (ResultRecord, RunConfig,
                                                                                      SettingManifest)}
    assert required[ResultRecord] == {"cell_id", "scene", "size", "weather", "method", "preset", "seed", "status"}
    assert required[RunConfig] == {"method", "scene", "seed", "config"}
    assert required[SettingManifest] == {"views"}
