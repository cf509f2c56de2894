"""Ground removal (``icpflow.scans.ground``): what each method calls ground, by class, against exact masks and labels.

    .venv/bin/python -m benchmarks.bench_ground [--sequences 8] [--methods local,both,patchwork]

* Synthetic world (the test split, ``--sequences`` sequences of 2 frames at 64 and at 32 beams, pc0 of each pair,
  within the 32 m crop; the world's exact masks): the share of the moving points called ground, by class (car,
  other vehicle, pedestrian, cyclist), of the static non-ground points called ground, and of the true ground kept as
  ground; milliseconds per scan (median).
* KITTI odometry sequence 01 frames 0-2 (lifted 1.73 m into the height frame): agreement with SemanticKITTI's road,
  parking, sidewalk, other-ground and terrain, and the share of the car points called ground.
* Argoverse 2's shipped sweep (ego frame, ground near z = -0.32 m; the av2 preset's frame): agreement with the
  official ``is_ground_0`` (within 0.3 m of the map's ground height, which the AV2 metrics leave out) and the share
  of the dynamic points called ground.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from benchmarks.common import DATA, GROUND_CLASSES, SEQ01
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.datasets.synthetic.scene import CLASSES
from icpflow.scans.ground import GroundSegmenter
from icpflow.scans.preprocess import HeightFrame, Preprocessing, lift_points
from icpflow.teacher.config import GroundConfig, ICPFlowConfig


def segmenter(settings: Preprocessing, method: str) -> GroundSegmenter:
    return GroundSegmenter(dataclasses.replace(settings, ground=dataclasses.replace(settings.ground, method=method)))


def synthetic_table(methods, sequences: int) -> None:
    pairs = []
    for beams in (64, 32):
        data = SyntheticDataset(split="test", num_sequences=sequences, frames_per_sequence=2, beams=beams)
        pairs += [data[i] for i in range(len(data))]
    print(f"\nSynthetic test split, {len(pairs)} scans (64 and 32 beams), within the 32 m crop: share called ground")
    names = [CLASSES[c] for c in (1, 2, 3, 4)]
    print(f"| method | moving | {' | '.join(names)} | static non-ground | true ground kept | ms per scan |")
    print("|---|---|" + "---|" * len(names) + "---|---|---|")
    for method in methods:
        find = segmenter(Preprocessing(), method)
        find(pairs[0].pc0)  # compiled kernels, a warm cache
        called, total, seconds = {}, {}, []
        for pair in pairs:
            inside = (np.abs(pair.pc0[:, :2]) < 32).all(axis=1)
            tic = time.perf_counter()
            mask = find(pair.pc0)
            seconds.append(time.perf_counter() - tic)
            moving = pair.dynamic & inside
            kinds = {
                "moving": moving,
                "static": ~pair.ground0 & ~pair.dynamic & inside,
                "ground": pair.ground0 & inside,
            }
            kinds.update({CLASSES[c]: moving & (pair.classes == c) for c in (1, 2, 3, 4)})
            for kind, members in kinds.items():
                called[kind] = called.get(kind, 0) + int((mask & members).sum())
                total[kind] = total.get(kind, 0) + int(members.sum())
        share = {kind: called[kind] / max(1, total[kind]) for kind in called}
        cells = " | ".join(f"{share[name]:.2%}" for name in names)
        print(
            f"| {method} | {share['moving']:.2%} | {cells} | {share['static']:.2%} | {share['ground']:.2%} | "
            f"{1000 * np.median(seconds):.1f} |"
        )
    print("points: " + ", ".join(f"{kind} {count}" for kind, count in total.items()))


def kitti_table(methods) -> None:
    if not SEQ01.is_file():
        print(f"\n(KITTI: {SEQ01} is absent)")
        return
    data = np.load(SEQ01)
    settings = Preprocessing(HeightFrame(0.0), GroundConfig(sensor_height=1.73))
    print("\nKITTI sequence 01 frames 0-2 against SemanticKITTI (road, parking, sidewalk, other-ground, terrain)")
    print("| method | agreement | ground share (labelled: road etc.) | car points called ground | ms per scan |")
    print("|---|---|---|---|---|")
    for method in methods:
        find = segmenter(settings, method)
        agree, share, labelled, cars, seconds = [], [], [], [], []
        for frame in range(3):
            points = lift_points(data[f"points{frame}"].astype(np.float32), 1.73)
            labels = data[f"labels{frame}"].reshape(-1)
            truth = np.isin(labels, GROUND_CLASSES)
            tic = time.perf_counter()
            mask = find(points)
            seconds.append(time.perf_counter() - tic)
            agree.append((mask == truth).mean())
            share.append(mask.mean())
            labelled.append(truth.mean())
            cars.append(mask[labels == 1].mean())
        print(
            f"| {method} | {np.mean(agree):.1%} | {np.mean(share):.1%} ({np.mean(labelled):.1%}) | "
            f"{np.mean(cars):.2%} | {1000 * np.median(seconds[1:]):.0f} |"
        )


def av2_table(methods) -> None:
    if not (DATA / "av2").is_dir():
        print(f"\n(AV2: {DATA / 'av2'} is absent)")
        return
    from icpflow.datasets.av2 import AV2Dataset

    pair = AV2Dataset(DATA / "av2", split="val").pair(0)
    settings = Preprocessing.from_teacher(ICPFlowConfig.preset("av2"))
    inside = (np.abs(pair.pc0[:, :2]) < 51.2).all(axis=1)
    print("\nArgoverse 2 sweep 0 against the official is_ground_0 (map ground + 0.3 m), within the 51.2 m crop")
    print("| method | agreement | dynamic points called ground |")
    print("|---|---|---|")
    for method in methods:
        mask = segmenter(settings, method)(pair.pc0)
        agreement = (mask == pair.ground0)[inside].mean()
        print(f"| {method} | {agreement:.1%} | {mask[pair.dynamic & inside].mean():.2%} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=8, help="synthetic sequences per beam count")
    parser.add_argument("--methods", default="local,both,patchwork")
    args = parser.parse_args()
    methods = args.methods.split(",")
    synthetic_table(methods, args.sequences)
    kitti_table(methods)
    av2_table(methods)


if __name__ == "__main__":
    main()
