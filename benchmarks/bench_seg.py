"""Segmentation speed with the shipped weights: scans/s including projection and back-projection.

CPU: one pinned core with 1 thread (the goal, issue 4: >= 40 scans/s median), 2 threads on 2 cores,
eager (BatchNorm folded, the Segmenter's default) and a frozen TorchScript trace; a batch of 8 scans;
the time split into projection, network and back-projection. GPU (when CUDA is present): batched scans/s
(goal >= 2000). ONNX Runtime and int8 are not measured: onnxruntime is not installed here and PyTorch's
dynamic int8 quantisation does not cover convolutions.
"""
from __future__ import annotations

import os
import time

import numpy as np

from benchmarks.common import median_ms, record, single_core


def _scans(n: int = 8):
    from topometric_ros.sim.frames import simulated_frames

    frames, _ = simulated_frames("office1", n, seed=11)
    return [(f.points, f.ring, f.intensity) for f in frames]


def main(repeats: int = 30) -> dict:
    single_core()
    import torch

    from topometric_ros.config import SegmentationConfig
    from topometric_ros.segmentation.infer import Segmenter
    from topometric_ros.segmentation.projection import project

    scans = _scans()
    seg = Segmenter.from_config(SegmentationConfig(threads=1))
    it = iter(range(10**9))
    results = {}

    def one():
        return seg.predict(*scans[next(it) % len(scans)])

    med, _ = median_ms(one, repeats=repeats)
    results["cpu1_eager_ms_median"] = round(med, 2)
    results["cpu1_eager_scans_per_s"] = round(1000 / med, 1)

    images = [project(*s) for s in scans]
    results["cpu1_projection_ms"] = round(median_ms(lambda: project(*scans[next(it) % len(scans)]), repeats)[0], 2)
    x = torch.from_numpy(images[0][0][None])
    with torch.inference_mode():
        results["cpu1_network_ms"] = round(median_ms(lambda: seg.model(x), repeats)[0], 2)
        out = seg.model(x).softmax(1).max(1)
    lab, conf = out[1].to(torch.uint8).numpy()[0], out[0].numpy()[0]
    proj = images[0][1]
    results["cpu1_backprojection_ms"] = round(median_ms(lambda: (proj.unproject(lab), proj.unproject(conf)), repeats)[0], 3)

    with torch.inference_mode():
        traced = torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.trace(seg.model, x)))
        diff = float((traced(x) - seg.model(x)).abs().max())
        results["cpu1_torchscript_network_ms"] = round(median_ms(lambda: traced(x), repeats)[0], 2)
        results["torchscript_max_abs_logit_diff"] = diff

    batch = scans[:8]
    med_b, _ = median_ms(lambda: seg.predict_batch(batch), repeats=max(3, repeats // 4))
    results["cpu1_batch8_scans_per_s"] = round(8000 / med_b, 1)

    if hasattr(os, "sched_setaffinity") and (os.cpu_count() or 1) >= 2:
        os.sched_setaffinity(0, set(range(os.cpu_count() or 1)))
        seg2 = Segmenter.from_config(SegmentationConfig(threads=2))
        med2, _ = median_ms(lambda: seg2.predict(*scans[next(it) % len(scans)]), repeats=repeats)
        results["cpu2_eager_ms_median"] = round(med2, 2)
        results["cpu2_eager_scans_per_s"] = round(1000 / med2, 1)
        torch.set_num_threads(1)

    if torch.cuda.is_available():
        gpu = Segmenter.from_config(SegmentationConfig(device="cuda"))
        big = [scans[i % len(scans)] for i in range(64)]
        gpu.predict_batch(big)
        torch.cuda.synchronize()
        t = time.perf_counter()
        for _ in range(5):
            gpu.predict_batch(big)
        torch.cuda.synchronize()
        results["gpu_batch64_scans_per_s"] = round(5 * 64 / (time.perf_counter() - t), 1)
        xs = torch.from_numpy(np.stack([project(*s)[0] for s in big])).cuda()
        with torch.inference_mode():
            gpu.model(xs)
            torch.cuda.synchronize()
            t = time.perf_counter()
            for _ in range(20):
                gpu.model(xs)
            torch.cuda.synchronize()
        results["gpu_network_only_batch64_scans_per_s"] = round(20 * 64 / (time.perf_counter() - t), 1)
        results["gpu"] = torch.cuda.get_device_name()
    else:
        results["gpu"] = "none (no CUDA device on this machine)"
    return record("seg", results)


if __name__ == "__main__":
    main()
