"""Segmentation speed with the shipped weights: scans/s including projection and back-projection.

CPU backends side by side (issue 4 goal: >= 40 scans/s median on one core): eager PyTorch (BatchNorm
folded) and ONNX Runtime (the default: the same checked weights exported in memory at load time), each
with 1 thread on one pinned core (wall-time and process-CPU-time medians; CPU time is the fairer number
when other jobs share the core) and 2 threads on 2 cores; per backend the label agreement with eager on
the benchmark scans. Also: the time split into projection, network (+ softmax read-out) and
back-projection; a frozen TorchScript trace and channels-last eager for reference; a batch of 8 scans.
GPU (when CUDA is present): batched scans/s (goal >= 2000). int8 is not measured here: PyTorch's dynamic
int8 does not cover convolutions, and ONNX Runtime static int8 (QDQ, tried once) agreed with fp32 on only
~89 % of labels (docs/results.md).
"""
from __future__ import annotations

import copy
import os
import time

import numpy as np

from benchmarks.common import median_ms, record, single_core


def _scans(n: int = 8):
    from topometric_ros.sim.frames import simulated_frames

    frames, _ = simulated_frames("office1", n, seed=11)
    return [(f.points, f.ring, f.intensity) for f in frames]


def _per_scan(seg, scans, repeats: int) -> float:
    """Median ms of Segmenter.predict over the scans in turn (projection + network + back-projection)."""
    it = iter(range(10**9))
    return median_ms(lambda: seg.predict(*scans[next(it) % len(scans)]), repeats=repeats)[0]


def _per_scan_cpu(seg, scans, repeats: int) -> float:
    """Median process CPU ms of Segmenter.predict: less sensitive than wall time to other jobs sharing the core."""
    for s in scans[:2]:
        seg.predict(*s)
    samples = []
    for k in range(repeats):
        t = time.process_time()
        seg.predict(*scans[k % len(scans)])
        samples.append(1000 * (time.process_time() - t))
    return float(np.median(samples))


def _agreement(seg, ref, scans) -> float:
    """Fraction of points whose label equals the reference segmenter's, over all scans."""
    same = total = 0
    for s in scans:
        a, b = seg.predict(*s)[0], ref.predict(*s)[0]
        same += int((a == b).sum())
        total += len(a)
    return same / total


def _cpu(results: dict, scans: list, repeats: int) -> None:
    import torch

    from topometric_ros.config import SegmentationConfig
    from topometric_ros.segmentation.infer import Segmenter, read_out
    from topometric_ros.segmentation.projection import project

    segs = {b: Segmenter.from_config(SegmentationConfig(threads=1, backend=b)) for b in ("eager", "onnxruntime")}
    eager = segs["eager"]
    for name, seg in segs.items():
        results[f"backend_{name}_runs"] = seg.backend
        med = _per_scan(seg, scans, repeats)
        results[f"cpu1_{name}_ms_median"] = round(med, 2)
        results[f"cpu1_{name}_scans_per_s"] = round(1000 / med, 1)
        results[f"cpu1_{name}_cpu_time_ms_median"] = round(_per_scan_cpu(seg, scans, repeats), 2)
        results[f"{name}_label_agreement_with_eager"] = round(_agreement(seg, eager, scans), 6)

    it = iter(range(10**9))
    results["cpu1_projection_ms"] = round(median_ms(lambda: project(*scans[next(it) % len(scans)]), repeats)[0], 2)
    image, proj = project(*scans[0])
    for name, seg in segs.items():
        results[f"cpu1_{name}_network_ms"] = round(median_ms(lambda: seg._run(image[None]), repeats)[0], 2)
    lab, conf = eager._run(image[None])
    results["cpu1_backprojection_ms"] = round(
        median_ms(lambda: (proj.unproject(lab[0]), proj.unproject(conf[0])), repeats)[0], 3)

    x = torch.from_numpy(image[None])
    with torch.no_grad():
        ref = read_out(eager.scorer(x).numpy())[0]
        traced = torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.trace(eager.scorer.eval(), x)))
        results["cpu1_torchscript_network_ms"] = round(median_ms(lambda: traced(x), repeats)[0], 2)
        results["torchscript_label_agreement_with_eager"] = float((read_out(traced(x).numpy())[0] == ref).mean())
        cl = copy.deepcopy(eager.scorer).to(memory_format=torch.channels_last)
        xc = x.contiguous(memory_format=torch.channels_last)
        results["cpu1_channels_last_network_ms"] = round(median_ms(lambda: cl(xc), repeats)[0], 2)
        results["channels_last_label_agreement_with_eager"] = float(
            (read_out(cl(xc).contiguous().numpy())[0] == ref).mean())

    batch = scans[:8]
    for name, seg in segs.items():
        med_b, _ = median_ms(lambda: seg.predict_batch(batch), repeats=max(3, repeats // 4))
        results[f"cpu1_{name}_batch8_scans_per_s"] = round(8000 / med_b, 1)

    if hasattr(os, "sched_setaffinity") and (os.cpu_count() or 1) >= 2:
        os.sched_setaffinity(0, set(range(os.cpu_count() or 1)))
        for name in ("eager", "onnxruntime"):
            seg2 = Segmenter.from_config(SegmentationConfig(threads=2, backend=name))
            med2 = _per_scan(seg2, scans, repeats)
            results[f"cpu2_{name}_ms_median"] = round(med2, 2)
            results[f"cpu2_{name}_scans_per_s"] = round(1000 / med2, 1)
            del seg2
        torch.set_num_threads(1)


def _gpu(results: dict, scans: list) -> None:
    import torch

    from topometric_ros.config import SegmentationConfig
    from topometric_ros.segmentation.infer import Segmenter
    from topometric_ros.segmentation.projection import project

    def scans_per_s(run, repeats: int, batch: int) -> float:
        """Scans per second of ``run`` (one batch of ``batch`` scans) after a warm-up, GPU work waited for."""
        run()
        torch.cuda.synchronize()
        t = time.perf_counter()
        for _ in range(repeats):
            run()
        torch.cuda.synchronize()
        return round(repeats * batch / (time.perf_counter() - t), 1)

    gpu = Segmenter.from_config(SegmentationConfig(device="cuda"))
    big = [scans[i % len(scans)] for i in range(64)]
    results["gpu_batch64_scans_per_s"] = scans_per_s(lambda: gpu.predict_batch(big), 5, 64)
    xs = torch.from_numpy(np.stack([project(*s)[0] for s in big])).cuda()
    with torch.inference_mode():
        results["gpu_network_only_batch64_scans_per_s"] = scans_per_s(lambda: gpu.model(xs), 20, 64)
    results["gpu"] = torch.cuda.get_device_name()


def main(repeats: int = 30) -> dict:
    single_core()
    import torch

    scans = _scans()
    results: dict = {}
    _cpu(results, scans, repeats)
    if torch.cuda.is_available():
        _gpu(results, scans)
    else:
        results["gpu"] = "none (no CUDA device on this machine)"
    return record("seg", results)


if __name__ == "__main__":
    main()
