"""`topometric train` and `topometric eval-seg` end to end on a small simulated bag."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from topometric_ros.cli import main


def _rows(path):
    with open(path) as f:
        return {r["group"]: r for r in csv.DictReader(f)}


def test_eval_seg_on_the_clouds_own_labels_is_perfect(office_bag, tmp_path, capsys):
    bag, _ = office_bag
    out = tmp_path / "labels"
    assert main(["eval-seg", str(bag), "--mode", "labels", "--every", "5", "--out", str(out)]) == 0
    rows = _rows(out / "per_class_iou.csv")
    assert float(rows["all"]["miou_paper"]) == 100.0 and float(rows["scene:office1"]["wall"]) == 100.0
    with open(out / "confusion.csv") as f:
        conf = [list(map(int, r[1:])) for r in list(csv.reader(f))[1:]]
    assert sum(map(sum, conf)) > 0 and all(conf[i][j] == 0 for i in range(7) for j in range(7) if i != j)
    assert (out / "confusion.png").stat().st_size > 1000
    assert json.loads((out / "metrics.json").read_text())["speed"]["scans"] == 0  # no network ran
    assert "miou_paper" in capsys.readouterr().out


def test_eval_seg_reads_another_cloud_topic_and_tells_same_named_bags_apart(office_bag, tmp_path):
    """A bag whose only PointCloud2 topic is not /points is read (as replay and inspect read it); bags are found
    anywhere below a folder given (as the audit finds them: simulate --split writes SENSOR/test/BAG); two bags
    of one name in different folders (two robots, or one per sensor) get rows of their own."""
    from topometric_ros import bag as bags

    src, _ = office_bag
    copies = []
    for robot in ("robot1", "robot2"):
        dst, clouds = tmp_path / robot / "test" / "office1_0", 0
        with bags.BagWriter(dst) as w:
            for topic, t_ns, msg in bags.read_messages(src):
                clouds += topic == "/points"
                if clouds > 4:
                    break
                w.write("/lidar/points" if topic == "/points" else topic, t_ns * 1e-9, msg)
        copies.append(dst)
    out = tmp_path / "out"
    assert main(["eval-seg", str(tmp_path), "--mode", "labels", "--out", str(out)]) == 0  # bags found below
    rows = _rows(out / "per_class_iou.csv")
    assert {"bag:robot1/test/office1_0", "bag:robot2/test/office1_0"} <= set(rows), list(rows)
    assert float(rows["all"]["miou_paper"]) == 100.0


@pytest.fixture(scope="module")
def trained(office_bag, tmp_path_factory):
    bag, _ = office_bag
    out = tmp_path_factory.mktemp("train")
    rc = main(["train", str(bag), "--epochs", "1", "--crops", "12", "--batch", "6", "--every", "10",
               "--seed", "3", "--out", str(out / "w"), "--cache", str(out / "cache")])
    return rc, out


def test_train_writes_loadable_weights_and_a_model_card(trained, office_bag, tmp_path):
    rc, out = trained
    assert rc == 0
    card = json.loads((out / "w" / "model_card.json").read_text())
    assert card["training"]["command"].startswith("topometric train ") and "--seed 3" in card["training"]["command"]
    assert card["training"]["seed"] == 3 and card["classes"][1] == "floor"
    assert len(card["training"]["history"]) == 1 and card["weights"]["sha256"]
    bag, _ = office_bag
    res = tmp_path / "net"
    assert main(["eval-seg", str(bag), "--weights", str(out / "w" / "rangenet.pt"), "--limit", "3",
                 "--out", str(res)]) == 0
    metrics = json.loads((res / "metrics.json").read_text())
    assert metrics["speed"]["scans"] == 2 and metrics["speed"]["scans_per_s"] > 0  # the first scan is warm-up


def test_quantize_calibrates_trained_weights_for_int8_and_eval_seg_says_which_ran(trained, office_bag, tmp_path,
                                                                                capsys):
    """`topometric quantize` writes the activation ranges beside freshly trained weights; eval-seg then runs
    them int8 when asked (and says so), float32 before."""
    import shutil

    _, out = trained
    bag, _ = office_bag
    weights = tmp_path / "rangenet.pt"
    shutil.copy(out / "w" / "rangenet.pt", weights)
    args = ["eval-seg", str(bag), "--weights", str(weights), "--limit", "2", "--precision", "int8"]
    assert main([*args, "--out", str(tmp_path / "before")]) == 0
    assert "float32 network" in capsys.readouterr().out  # no ranges yet: float32, with the reason logged
    assert main(["quantize", str(bag), "--weights", str(weights), "--every", "5"]) == 0
    said = capsys.readouterr().out
    assert "rangenet.int8.json" in said and (tmp_path / "rangenet.int8.json").is_file()
    assert "activation ranges of 6 range images" in said and "note: 6 range image(s) are few" in said  # 30 scans / 5
    assert main([*args, "--out", str(tmp_path / "after")]) == 0
    assert "int8 network" in capsys.readouterr().out


def test_eval_seg_with_tampered_weights_is_a_clear_error(trained, office_bag, tmp_path, capsys):
    _, out = trained
    bad = out / "w" / "rangenet.pt"
    data = bytearray(bad.read_bytes())
    data[len(data) // 2] ^= 0xFF
    (tmp_path / "rangenet.pt").write_bytes(bytes(data))
    bag, _ = office_bag
    assert main(["eval-seg", str(bag), "--weights", str(tmp_path / "rangenet.pt"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and ("checksum mismatch" in err or "not a safe torch weights file" in err)


def test_train_with_validation_keeps_the_best_epoch_and_stops_at_the_time_budget(office_bag, tmp_path, capsys):
    bag, _ = office_bag
    out = tmp_path / "w"
    assert main(["train", str(bag), "--val", str(bag), "--epochs", "3", "--crops", "6", "--batch", "6",
                 "--every", "10", "--seed", "1", "--context", "4,8", "--max-minutes", "60",
                 "--out", str(out), "--cache", str(tmp_path / "cache")]) == 0
    assert "note: 1 validation bag(s) are training bags too (office1_rt)" in capsys.readouterr().out
    card = json.loads((out / "model_card.json").read_text())
    hist = card["training"]["history"]
    best = max(range(len(hist)), key=lambda i: (hist[i]["val_miou"], i))  # ties: the later epoch
    assert len(hist) == 3 and card["training"]["selected_epoch"] == best + 1
    assert card["metrics"]["val"]["val_miou"] == hist[best]["val_miou"] and card["model"]["context"] == [4, 8]
    out0 = tmp_path / "w0"  # a zero-minute budget: one step, one (partial) epoch, still a loadable card
    assert main(["train", str(bag), "--epochs", "5", "--crops", "6", "--batch", "6", "--every", "10",
                 "--max-minutes", "1e-9", "--out", str(out0), "--cache", str(tmp_path / "cache")]) == 0
    assert len(json.loads((out0 / "model_card.json").read_text())["training"]["history"]) == 1


def test_train_from_weights_starts_there_and_records_the_parent(trained, office_bag, tmp_path, capsys):
    from topometric_ros.segmentation.checkpoint import load_weights

    _, out = trained
    parent = out / "w" / "rangenet.pt"
    parent_card, parent_state = load_weights(parent)
    bag, _ = office_bag
    child = tmp_path / "ft"
    # --widths/--context differ from the parent's network: the parent's network is what is trained
    assert main(["train", str(bag), "--init", str(parent), "--widths", "8,8,8", "--epochs", "1", "--crops", "6",
                 "--batch", "6", "--every", "10", "--lr", "0", "--out", str(child),
                 "--cache", str(out / "cache")]) == 0
    card, state = load_weights(child / "rangenet.pt")
    init = card["training"]["init"]
    assert init["weights"] == str(parent) and init["command"] == parent_card["training"]["command"]
    assert init["seed"] == 3 and card["model"] == parent_card["model"]
    # lr 0: the optimiser never moved a weight, so the child holds the parent's tensors (BatchNorm statistics
    # still follow the new batches)
    moved = [k for k in parent_state if "running" not in k and "num_batches" not in k
             and not (state[k] == parent_state[k]).all()]
    assert not moved
    assert main(["train", str(bag), "--init", str(tmp_path / "missing.pt"), "--epochs", "1", "--out",
                 str(tmp_path / "x"), "--cache", str(out / "cache")]) == 2
    assert "segmentation weights not found" in capsys.readouterr().err


def test_cache_built_in_worker_processes_equals_the_one_built_in_process(office_bag, tmp_path):
    from topometric_ros.segmentation.data import build_cache

    bag, _ = office_bag
    one = build_cache([bag, bag], tmp_path / "one.npz", every=10, progress=False)
    two = build_cache([bag, bag], tmp_path / "two.npz", every=10, progress=False, workers=2)
    assert one.keys() == two.keys() and len(one) == 1
    for shape, g in one.items():
        assert len(g["images"]) == 2 * 3  # scans 0, 10, 20 of each copy, in bag order
        for key in ("images", "labels", "scene", "sensor"):
            np.testing.assert_array_equal(g[key], two[shape][key])


@pytest.mark.parametrize("device, reason", [("tpu", "unknown training device"), ("cuda:0", "no CUDA device")])
def test_train_on_a_device_this_machine_lacks_is_a_clear_error(office_bag, tmp_path, capsys, device, reason):
    import torch

    if device.startswith("cuda") and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    bag, _ = office_bag
    assert main(["train", str(bag), "--device", device, "--epochs", "1", "--out", str(tmp_path / "w"),
                 "--cache", str(tmp_path / "cache")]) == 2
    assert reason in capsys.readouterr().err
    assert not (tmp_path / "cache").exists()  # refused before any work


def test_blend_writes_mixed_weights_and_refuses_another_network_or_a_bad_alpha(trained, tmp_path, capsys):
    from topometric_ros.segmentation.checkpoint import SHIPPED, load_weights

    rc, out = trained
    assert rc == 0
    tuned = out / "w" / "rangenet.pt"
    assert main(["blend", str(tuned), str(tuned), "--alpha", "0.3", "--out", str(tmp_path / "b")]) == 0
    card, state = load_weights(tmp_path / "b" / "rangenet.pt")
    assert all(v.equal(load_weights(tuned)[1][k]) for k, v in state.items())  # a blend of one network with itself
    assert card["training"]["blend"]["command"].startswith("topometric blend ")
    assert "topometric quantize" in capsys.readouterr().out
    assert main(["blend", str(SHIPPED), str(tuned), "--out", str(tmp_path / "c")]) == 2  # another context width
    assert "different networks" in capsys.readouterr().err and not (tmp_path / "c").exists()
    with pytest.raises(SystemExit) as e:
        main(["blend", str(SHIPPED), str(tuned), "--alpha", "2", "--out", str(tmp_path / "c")])
    assert e.value.code == 2 and "expected a number within [0, 1], got '2'" in capsys.readouterr().err


def test_blend_refuses_to_write_over_the_weights_it_reads(trained, office_bag, tmp_path, capsys):
    """--out the tuned weights' own folder would replace them with the blend (a rerun then blends a blend)."""
    rc, out = trained
    tuned = out / "w" / "rangenet.pt"
    before = tuned.read_bytes()
    assert main(["blend", str(tuned), str(tuned), "--out", str(out / "w")]) == 2
    assert "holds the parent weights" in capsys.readouterr().err and tuned.read_bytes() == before
    assert main(["eval-seg", str(office_bag[0]), "--weights", str(out / "w"), "--out", str(tmp_path / "e")]) == 2
    assert f"is a folder; give the weights file in it ({out / 'w' / 'rangenet.pt'})" in capsys.readouterr().err


@pytest.mark.parametrize("extra, words", [
    (["--widths", "8,8"], "--widths: expected 3 whole numbers > 0 separated by commas, got '8,8'"),
    (["--widths", "0,8,8"], "--widths: expected 3 whole numbers > 0"),
    (["--widths", "abc"], "--widths: expected 3 whole numbers > 0"),
    (["--context", "0,0"], "--context: expected 2 whole numbers > 0"),
    (["--context", "2"], "--context: expected 2 whole numbers > 0"),
    (["--init", "missing.pt"], "segmentation weights not found: missing.pt"),
])
def test_train_refuses_a_bad_network_or_start_before_building_the_cache(office_bag, tmp_path, capsys, cli_exit_code,
                                                                        extra, words):
    """Each was a torch traceback, an unpacking error that named no option, or (--init) a failure after the
    projected-scan cache was built (minutes to hours on a real training set)."""
    bag, _ = office_bag
    assert cli_exit_code(["train", str(bag), "--out", str(tmp_path / "w"), "--cache", str(tmp_path / "cache"),
                       *extra]) == 2
    assert words in capsys.readouterr().err
    assert not (tmp_path / "cache").exists() and not (tmp_path / "w").exists()


def test_train_refuses_a_cache_inside_a_bag(office_bag, tmp_path, capsys):
    bag, _ = office_bag
    before = sorted(p.name for p in bag.iterdir())
    assert main(["train", str(bag), "--out", str(tmp_path / "w"), "--cache", str(bag / "cache")]) == 2
    assert f"--cache {bag / 'cache'} is inside the bag folder" in capsys.readouterr().err
    assert sorted(p.name for p in bag.iterdir()) == before


def test_train_without_progress_draws_no_bars(office_bag, tmp_path, capsys):
    from topometric_ros.segmentation.train import TrainConfig, train

    bag, _ = office_bag
    card = train([bag], tmp_path / "w", TrainConfig(epochs=1, crops_per_epoch=12, batch=6, every=10),
                 cache_dir=tmp_path / "cache", progress=False)
    assert len(card["training"]["history"]) == 1
    err = capsys.readouterr().err
    assert "epoch 1/1" not in err and "cache bags" not in err, err  # the per-step bar and the cache bar


def test_eval_seg_of_one_scan_says_its_speed_was_not_measured(trained, office_bag, tmp_path, capsys):
    """Each sensor's first scan is warm-up: with one scan the speed line used to vanish without a word."""
    rc, out = trained
    assert main(["eval-seg", str(office_bag[0]), "--weights", str(out / "w" / "rangenet.pt"), "--limit", "1",
                 "--out", str(tmp_path / "e")]) == 0
    assert "speed: not measured (each sensor's first scan is left out as warm-up" in capsys.readouterr().out
