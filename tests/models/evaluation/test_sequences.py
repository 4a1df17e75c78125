"""Cross-season protocol on generated image sequences: pairing, feature cache, methods, CLI."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from models.evaluation import seqslam as seq
from models.evaluation import sequences
from models.evaluation.seqslam import seqslam
from models.frontend.embedding import Embedder
from service.cli import app


def write_sequences(root, n: int = 24, seed: int = 0):
    """A 'route' of n places; the query season is the database darkened with noise."""
    rng = np.random.default_rng(seed)
    db, q = root / "summer", root / "winter"
    db.mkdir()
    q.mkdir()
    for i in range(n):
        place = cv2.resize(rng.integers(0, 256, (8, 16, 3), dtype=np.uint8), (64, 32),
                           interpolation=cv2.INTER_CUBIC)
        winter = np.clip(place.astype(np.float32) * 0.7 + rng.normal(0, 6, place.shape), 0, 255)
        cv2.imwrite(str(db / f"images-{i:05d}.png"), place)
        cv2.imwrite(str(q / f"images-{i:05d}.png"), winter.astype(np.uint8))
    (db / "only-in-summer.png").write_bytes((db / "images-00000.png").read_bytes())
    return db, q


@pytest.fixture(autouse=True)
def no_installed_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "no-weights"))


def test_pairs_by_name_offset_and_limit(tmp_path):
    db, q = write_sequences(tmp_path, n=10)
    names = sequences.paired_names(db, q)
    assert len(names) == 10 and "only-in-summer.png" not in names
    assert sequences.paired_names(db, q, offset=3, limit=4) == names[3:7]
    with pytest.raises(ValueError, match="offset"):
        sequences.paired_names(db, q, offset=50)
    with pytest.raises(ValueError, match="not a folder"):
        sequences.paired_names(db, tmp_path / "nope")


def test_features_are_cached_by_content(tmp_path):
    db, _ = write_sequences(tmp_path, n=6)
    enc = Embedder({"resize": "squash", "slsbh": {"k": 16}})
    paths = [db / n for n in sorted(p.name for p in db.glob("images-*.png"))]
    a = sequences.cached_features(enc, paths, tmp_path / "cache")
    assert len(list((tmp_path / "cache").glob("features-*.npy"))) == 1
    np.testing.assert_array_equal(sequences.cached_features(enc, paths, tmp_path / "cache"), a)
    cv2.imwrite(str(paths[0]), np.zeros((32, 64, 3), np.uint8))  # content changed: new key
    sequences.cached_features(enc, paths, tmp_path / "cache")
    assert len(list((tmp_path / "cache").glob("features-*.npy"))) == 2


def test_every_method_scores_and_sequence_methods_use_order():
    rng = np.random.default_rng(0)
    n, d = 40, 64
    db = rng.normal(size=(n, d)).astype(np.float32)
    q = db + rng.normal(0, 3.0, size=(n, d)).astype(np.float32)  # weak single-image similarity
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    frames = (np.round(db * 20), np.round(q * 20))  # stand-ins for patch-normalised pixels
    res = sequences.image_experiment(db, q, methods=list(sequences.METHODS), preset="cortexloc-grid",
                                     k=256, s=0.05, seeds=2, frames=frames)
    m = res["methods"]
    assert set(m) == set(sequences.METHODS)
    for entry in m.values():
        for key in ("auc", "query_auc", "recall_at_1", "recall_at_5", "recall_at_100p"):
            assert 0.0 <= entry[f"{key}_min"] <= entry[f"{key}_mean"] <= entry[f"{key}_max"] <= 1.0
    assert m["cosine-seq"]["auc_mean"] > m["cosine"]["auc_mean"]
    assert m["cosine-seq"]["recall_at_1_mean"] > m["cosine"]["recall_at_1_mean"]
    assert m["openseqslam"]["recall_at_1_mean"] > 0.9 and m["openseqslam"]["ds"] == 10
    # Every method is scored on the same queries: those with a full window of ds frames.
    assert res["queries"] == np.flatnonzero(seq.full_window(n, 10)).tolist()
    assert len(m["htm"]["per_seed"]) == 2 and len(m["cosine"]["per_seed"]) == 1
    assert 0.0 <= m["htm"]["query_predicted_fraction_mean"] <= 1.0
    assert res["first"]["htm"]["S"].shape == (n, n)


def test_chance_prediction_rate_is_far_below_the_in_order_rate():
    """docs/design/science.md §3.8: shuffled query frames are predicted only by chance; true order by
    sequence."""
    rng = np.random.default_rng(1)
    codes = np.stack([np.sort(rng.choice(2048, 40, replace=False)) for _ in range(60)])
    _, q_w, info = sequences.run_tm(codes, codes, "cortexloc-grid", seed=3, reset=True, width=2048)
    assert len(q_w) == 60
    assert info["query_predicted_fraction"] > 0.9
    assert info["chance_predicted_fraction"] < 0.1


def test_adaptation_is_applied_to_every_method():
    rng = np.random.default_rng(2)
    n, d = 30, 64
    places = rng.normal(size=(n, d))
    # A large season-wide offset hides the places from single-image cosine; adaptation removes it.
    db = (places + 8 * rng.normal(size=d)).astype(np.float32)
    q = (places + 0.5 * rng.normal(size=(n, d)) + 8 * rng.normal(size=d)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    plain = sequences.image_experiment(db, q, methods=["cosine"], preset="cortexloc-grid", seeds=1)
    adapted = sequences.image_experiment(db, q, methods=["cosine"], preset="cortexloc-grid", seeds=1,
                                         adapt_tau=5)
    assert adapted["methods"]["cosine"]["recall_at_1_mean"] > plain["methods"]["cosine"]["recall_at_1_mean"]


def test_a_reversed_query_keeps_places_aligned():
    rng = np.random.default_rng(3)
    db = rng.normal(size=(20, 32)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    fwd = sequences.image_experiment(db, db, methods=["cosine", "htm"], preset="cortexloc-grid", k=64, s=0.1,
                                     seeds=1, reset=True)
    rev = sequences.image_experiment(db, db, methods=["cosine", "htm"], preset="cortexloc-grid", k=64, s=0.1,
                                     seeds=1, reset=True, reverse_query=True)
    np.testing.assert_allclose(rev["first"]["cosine"]["S"], fwd["first"]["cosine"]["S"], atol=1e-6)
    assert rev["methods"]["cosine"]["recall_at_1_mean"] == 1.0
    # The TM's context-specific cells differ when the same places come in the other order.
    assert rev["methods"]["htm"]["auc_mean"] < fwd["methods"]["htm"]["auc_mean"]


def test_tolerance_counts_neighbours():
    S = np.zeros((5, 5))
    S[np.arange(4) + 1, np.arange(4)] = 1.0  # every query's best match is off by one
    S[3, 4] = 1.0
    assert sequences.evaluate(S, 0)["recall_at_1"] == 0.0
    assert sequences.evaluate(S, 1)["recall_at_1"] == 1.0
    assert sequences.evaluate(S, 1)["query_auc"] > sequences.evaluate(S, 0)["query_auc"]


def test_evaluation_scores_only_full_paths_and_given_answers():
    S = np.zeros((6, 6))
    S[np.arange(6), np.arange(6)] = 1.0
    S[:, 0] = -np.inf  # no full path for query 0
    cols = np.array([False, True, True, True, True, False])
    r = sequences.evaluate(S, 0, columns=cols)
    assert r["recall_at_1"] == 1.0 and len(r["best"]) == 4
    # A method's own answers (OpenSeqSLAM) replace the argmax: all wrong here.
    best = np.zeros(6, dtype=np.int64)
    r = sequences.evaluate(S, 0, columns=cols, answers=(best, np.ones(6)))
    assert r["recall_at_1"] == 0.0 and r["query_auc"] == 0.0


def test_memory_methods_bring_their_ablations():
    assert sequences.with_ablations(["htm-seq"]) == ["cosine-seq", "slsbh-seq", "htm-seq"]
    assert sequences.with_ablations(["openseqslam", "htm", "mcn-seq", "slsbh"]) == [
        "openseqslam", "cosine", "slsbh", "htm", "cosine-seq", "slsbh-seq", "mcn-seq"]
    rng = np.random.default_rng(5)
    db = rng.normal(size=(24, 32)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    res = sequences.image_experiment(db, db, methods=["htm-seq"], preset="cortexloc-grid", k=64, s=0.1,
                                     seeds=1)
    assert list(res["methods"]) == ["cosine-seq", "slsbh-seq", "htm-seq"]


def test_eval_images_command(tmp_path):
    db, q = write_sequences(tmp_path, n=20)
    out = tmp_path / "r.json"
    # AlexNet without its weights (none in the tests): random ones, labelled so in the results
    r = CliRunner().invoke(app, ["eval", "images", "--db", str(db), "--query", str(q), "--resize", "squash",
                                 "--methods", "cosine,htm,openseqslam,cosine-seq", "--preset",
                                 "cortexloc-grid", "--s", "0.02", "--seeds", "2", "--ds", "6", "--cache",
                                 str(tmp_path / "c"), "--json", str(out), "--plots", str(tmp_path / "p"),
                                 "--backbone", "alexnet"])
    assert r.exit_code == 0, r.output
    payload = json.loads(out.read_text())
    assert list(payload["methods"]) == ["cosine", "slsbh", "htm", "openseqslam", "cosine-seq"]
    assert payload["config"]["pairs"] == 20 and payload["config"]["weights"] == "random"
    assert payload["config"]["ds"] == 6 and len(payload["queries"]) == 20 - 6 + 1
    cosine = payload["methods"]["cosine"]
    assert cosine["auc_mean"] > 0.5  # the seasons differ only by light and noise
    assert {"query_auc_mean", "query_auc_min", "query_auc_max", "recall_at_1_mean"} <= set(cosine)
    for name in ("pr.png", "pr_query.png", "gallery_htm.png", "gallery_openseqslam.png"):
        assert (tmp_path / "p" / name).stat().st_size > 0
    assert "all pairs" in r.output and "per query" in r.output
    bad = CliRunner().invoke(app, ["eval", "images", "--db", str(db), "--query", str(q), "--methods", "x"])
    assert bad.exit_code == 2


def test_eval_images_drops_dark_pairs(tmp_path):
    db, q = write_sequences(tmp_path, n=12)
    for name in ("images-00003.png", "images-00007.png"):  # a tunnel in winter only, and in both
        cv2.imwrite(str(q / name), np.full((32, 64, 3), 5, np.uint8))
    cv2.imwrite(str(db / "images-00007.png"), np.full((32, 64, 3), 5, np.uint8))
    out = tmp_path / "r.json"
    r = CliRunner().invoke(app, ["eval", "images", "--db", str(db), "--query", str(q), "--methods", "cosine",
                                 "--drop-dark", "20", "--adapt", "4", "--cache", str(tmp_path / "c"),
                                 "--json", str(out)])
    assert r.exit_code == 0, r.output
    config = json.loads(out.read_text())["config"]
    assert config["pairs"] == 10 and config["drop_dark"] == 20 and config["adapt_tau"] == 4


def test_sequence_filtered_methods_gain_from_order_and_keep_their_base():
    """X-seq is X's own similarity through the seqslam filter: it must use the frame order."""
    rng = np.random.default_rng(4)
    n, d = 60, 64
    db = rng.normal(size=(n, d)).astype(np.float32)
    q = db + rng.normal(0, 4.0, size=(n, d)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    res = sequences.image_experiment(db, q, methods=["slsbh", "slsbh-seq", "htm", "htm-seq"],
                                     preset="cortexloc-default", k=256, s=0.15, seeds=1, reset=True)
    m, first = res["methods"], res["first"]
    assert m["slsbh-seq"]["auc_mean"] > 2 * m["slsbh"]["auc_mean"]
    assert m["htm-seq"]["auc_mean"] > 2 * m["htm"]["auc_mean"]
    np.testing.assert_allclose(first["htm-seq"]["S"], seqslam(first["htm"]["S"], 10))
    assert m["htm-seq"]["preset"] == "cortexloc-default" and "query_predicted_fraction_mean" in m["htm-seq"]
    # The winner cells carry the previous step's context, which the filter's straight lines add up.
    assert m["htm-seq"]["auc_mean"] > m["slsbh-seq"]["auc_mean"]


def test_eval_images_defaults_follow_the_service(tmp_path):
    from service.frontend import resolve_backbone
    from service.maps.config import DEFAULT_RESIZE, MapOptions, resolve
    from service.settings import Settings

    db, q = write_sequences(tmp_path, n=14)
    out = tmp_path / "r.json"
    r = CliRunner().invoke(app, ["eval", "images", "--db", str(db), "--query", str(q), "--methods", "cosine",
                                 "--seeds", "1", "--cache", str(tmp_path / "c"), "--json", str(out)])
    assert r.exit_code == 0, r.output
    config = json.loads(out.read_text())["config"]
    assert config["preset"] == Settings().default_preset
    # no AlexNet weights are installed in the tests (conftest): the default is EfficientNet-Lite0's block
    assert config["backbone"] == resolve_backbone(Settings()).backbone == "efficientnet-lite0-s5"
    # a new map's resize, as the service resolves it
    new_map = resolve(MapOptions(), default_preset=config["preset"], default_backbone=config["backbone"])
    assert config["resize"] == DEFAULT_RESIZE == new_map.resize
    assert f"preset {config['preset']}, backbone {config['backbone']}" in r.output
    assert f"resize {config['resize']}" in r.output


def test_eval_images_reads_ground_truth_from_a_csv(tmp_path):
    db, q = write_sequences(tmp_path, n=12)
    names = sequences.image_names(q)
    gt = tmp_path / "gt.csv"
    # The database folder holds one file more than the query folder: indices count in each own list.
    db_names = sequences.image_names(db)
    # As VPR data sets write it, some rows name the file with its folder: `query/images-00000.png`.
    rows = [f"{i},{'query/' * (i % 2)}{n},{db_names.index(n)}" for i, n in enumerate(names)]
    gt.write_text("query_index,query_file,matching_ref_indices\n" + "\n".join(rows) + "\n")
    out = tmp_path / "r.json"
    args = ["eval", "images", "--db", str(db), "--query", str(q), "--methods", "cosine", "--resize", "squash",
            "--seeds", "1", "--cache", str(tmp_path / "c"), "--json", str(out), "--gt", str(gt)]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    payload = json.loads(out.read_text())
    assert payload["methods"]["cosine"]["recall_at_1_mean"] > 0.9 and payload["config"]["gt"] == str(gt)
    wrong = tmp_path / "wrong.csv"
    wrong.write_text(f"0,not-{names[0]},0\n")
    r = CliRunner().invoke(app, [*args[:-1], str(wrong)])
    assert r.exit_code == 2 and "not-images-00000.png" in r.output
    r = CliRunner().invoke(app, [*args, "--limit", "5"])
    assert r.exit_code == 2


def test_eval_images_encodes_only_the_window(tmp_path):
    db, q = write_sequences(tmp_path, n=20)
    out, cache = tmp_path / "r.json", tmp_path / "c"
    r = CliRunner().invoke(app, ["eval", "images", "--db", str(db), "--query", str(q), "--methods", "cosine",
                                 "--offset", "3", "--limit", "6", "--seeds", "1", "--ds", "4", "--cache",
                                 str(cache), "--json", str(out)])
    assert r.exit_code == 0, r.output
    config = json.loads(out.read_text())["config"]
    assert (config["pairs"], config["first"]) == (6, "images-00003.png")
    cached = sorted(cache.glob("features/features-*.npy"))
    assert [np.load(f).shape[0] for f in cached] == [6, 6]  # the database's window and the query's


def _entry(auc: float) -> dict[str, float]:
    keys = ("auc_mean", "auc_sd", "auc_min", "auc_max", "recall_at_1_mean", "recall_at_5_mean",
            "recall_at_100p_mean", "query_auc_mean", "query_recall_at_100p_mean", "seconds_mean")
    return dict.fromkeys(keys, auc)


def _right_edges(line: str, header: str, labels: list[str]) -> list[str]:
    """The character of `line` at each header label's last column, and the one after it."""
    ends = [header.index(label) + len(label) for label in labels]
    return [line[e - 1:e + 1] for e in ends]


def test_result_tables_align_their_columns_and_explain_auc_pairs():
    from service.cli.evaluate import format_grid_table, format_images_table

    methods = {"cosine": _entry(0.5), "service-without-tm": _entry(0.9876), "online-cosine": _entry(12345.0)}
    config = {"db": "summer", "query": "winter", "pairs": 20, "first": "a", "last": "b",
              "gt": "same file name", "tolerance": 0, "preset": "p", "backbone": "b", "weights": "random",
              "resize": "crop", "s": 0.25, "adapt_tau": 0, "reset": False, "seeds": 1, "ds": 10}
    images = format_images_table({"config": config, "methods": methods, "queries": [1, 2]})
    grid = format_grid_table({"data": {"source": "published", "sdr_file": "x.txt"}, "scoring": "paper",
                              "seeds": 1, "methods": methods})
    image_labels = ["AUC pairs", "min", "max", "AUC query", "R@1", "R@5", "R@100P", "s/run"]
    grid_labels = ["AUC pairs", "sd", "min", "max", "R@1", "R@5", "R@100P", "qAUC", "qR@100P"]
    for text, labels in ((images, image_labels), (grid, grid_labels)):
        lines = text.splitlines()
        header = next(line for line in lines if line.startswith("method "))
        rows = [line for line in lines if line.split(" ")[0] in methods]
        assert len(rows) == 3
        for row in rows:  # every number ends where its column's label ends, a blank after it
            assert all(pair[0] != " " and pair[1] == " " for pair in _right_edges(row, header, labels)), (
                f"{row!r} against {header!r}")
        assert "AUC pairs = the paper's AUC" in text and "near 0.5 beside R@1 1.000" in text


def test_eval_images_openseqslam_alone_runs_no_backbone(tmp_path):
    db, q = write_sequences(tmp_path, n=16)
    out = tmp_path / "r.json"
    r = CliRunner().invoke(app, ["eval", "images", "--db", str(db), "--query", str(q), "--methods",
                                 "openseqslam", "--ds", "4", "--seeds", "1", "--cache", str(tmp_path / "c"),
                                 "--json", str(out)])
    assert r.exit_code == 0, r.output
    payload = json.loads(out.read_text())
    assert payload["config"]["encoder"] == "none" and not (tmp_path / "c").exists()
    assert payload["methods"]["openseqslam"]["recall_at_1_mean"] > 0.9


def test_eval_images_refuses_a_sparsity_outside_the_slsbh_rules(tmp_path):
    """--s is checked by the one home of the sLSBH rules (presets.SlsbhParams), before any image is read."""
    from typer.testing import CliRunner

    from service.cli import app

    for bad in ("0.7", "0"):
        result = CliRunner().invoke(app, ["eval", "images", "--db", str(tmp_path), "--query", str(tmp_path),
                                          "--s", bad])
        assert result.exit_code == 2 and "--s" in result.output


def _readme_defaults(command: str) -> dict[str, str | bool]:
    """The options the README's command list states as defaults for `cortexloc eval COMMAND`: its
    `# defaults: --opt value --flag ...` comment, up to the first parenthesis."""
    from pathlib import Path

    lines = (Path(__file__).resolve().parents[3] / "README.md").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"cortexloc eval {command} "))
    stated = next(line for line in lines[start:] if "# defaults:" in line)
    tokens = stated.split("# defaults:", 1)[1].split("(", 1)[0].replace(",", " ").split()
    out: dict[str, str | bool] = {}
    for i, token in enumerate(tokens):
        if token.startswith("--"):
            value = tokens[i + 1] if i + 1 < len(tokens) and not tokens[i + 1].startswith("--") else None
            out[token] = value if value is not None else True
    return out


@pytest.mark.parametrize("command", ["grid", "images"])
def test_the_readme_states_the_eval_defaults(command):
    import typer.main

    params = typer.main.get_command(app).commands["eval"].commands[command].params
    stated = _readme_defaults(command)
    assert {"--seeds"} <= set(stated) and (command == "grid" or "--no-reset" in stated)
    for option, value in stated.items():
        param = next(p for p in params if option in (*p.opts, *p.secondary_opts))
        if value is True:  # a flag: --reset or --no-reset
            assert param.default is (option in param.opts), option
        else:
            assert str(param.default) == value, option
