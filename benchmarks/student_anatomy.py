"""Where a student's dynamic error is: per class, per object speed and extent, and what per-object oracles would
gain, beside the teacher and ego-only on the same pairs (issue 29's anatomy; issue 30's per-extent teacher table).

    .venv/bin/python -m benchmarks.student_anatomy --model student=<export dir or .ckpt> [--model NAME=PATH ...]
        [--refine NAME] [--teacher] [--cache teacher_flows.npz] [--set split=test --set dataset.reader.num_sequences=16]
        [--labels <label.py out_dir>] [--curves <train.py out_dir>]

Every ``--set`` is an ``eval.py`` override: any dataset with ground-truth flow, classes and instance ids works (the
synthetic world by default, ``eval.py``'s test split of 16 sequences = 64 pairs). Points scored are the paper's
dynamic foreground of ``eval.py`` (non-ground, inside the dataset's ``eval_crop``, true residual speed > 0.5 m/s,
class > 0). Methods: ``ego`` (ego flow only), ``teacher`` (``--teacher``: the dataset's teacher as ``eval.py`` runs
it; its flows are kept in ``--cache`` and reused), each ``--model`` (the Predictor on the pair's given ego motion
and ground, as ``eval.py``'s ``student`` with ``precision=f32``), and ``NAME+refine`` for each ``--refine NAME``
(the same model with the Predictor's ICP refinement, ``fastflow3d.inference.refine``), and ``labels``
(``--labels``: the pseudo-labels ``label.py`` stored for these very pairs, e.g. a student's own training pairs with
``--set split=train``; issue 43's fit).

Prints, per method:
1. per ground-truth class: share of the dynamic points, EPE (m), the median over points of
   ``|predicted residual| / |true residual|`` (the speed ratio: 1 = the right amount of motion, below 1 too slow);
2. the oracles: dynamic EPE with each true object's predicted flow replaced by its mean, and by the best rigid
   motion of the object fitted to the predicted flow (``geometry.kabsch``): what per-object smoothing could gain;
3. per object (moving instances with >= 5 dynamic points), by true speed and by extent (the object's pc0 points'
   length along their main horizontal axis): objects, share of points, point-weighted EPE and the median over
   objects of each object's median speed ratio;
4. with ``--labels``: the fit, each method against the labels instead of the truth (per class: EPE (m) and the
   median speed ratio to the labels' own residual motion): how far a student is from reproducing what it was taught,
   beside how far the labels are from the truth;
5. with ``--curves``: a training run's curves from its TensorBoard events (the training loss averaged over each
   validation interval, the validation loss and dynamic-foreground EPE at each validation).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.common import open_split
from icpflow.core.geometry import ego_flow, kabsch, rigid_flow
from icpflow.evaluation.metrics import PairTruth

SPEED_BINS = (0.5, 3.0, 8.0, 15.0, 40.0)  # m/s
EXTENT_BINS = (0.0, 2.0, 5.0, 8.0, 20.0)  # m
MIN_OBJECT_POINTS = 5


def teacher_flows(dataset, cfg, cache: Path | None) -> dict[str, np.ndarray]:
    """sample id -> the teacher's FULL flow (N0, 3) of each pair, from ``cache`` where it holds the id."""
    from icpflow.core.atomic import atomic_path
    from icpflow.evaluation.methods import TeacherMethod
    from icpflow.teacher import ICPFlow
    from icpflow.teacher.config import teacher_config

    stored = dict(np.load(cache)) if cache is not None and cache.is_file() else {}
    method = None
    for index in range(len(dataset)):
        sample_id = dataset.sample_id(index)
        if sample_id not in stored:
            method = method or TeacherMethod(ICPFlow(teacher_config(cfg)), dataset)
            stored[sample_id] = method(dataset[index], index).astype(np.float32)
    if cache is not None and method is not None:
        with atomic_path(cache) as temporary:
            with open(temporary, "wb") as handle:
                np.savez(handle, **stored)
    return stored


def object_extent(points: np.ndarray) -> float:
    """Length (m) of (N, 3) points along their main horizontal axis (the largest principal axis of x, y)."""
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    if len(xy) < 2:
        return 0.0
    axis = np.linalg.eigh(xy.T @ xy)[1][:, -1]
    along = xy @ axis
    return float(along.max() - along.min())


def rigid_oracle(points: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """(N, 3) flow of the rigid motion that best maps ``points`` onto ``points + flow`` (least squares)."""
    if len(points) < 3:
        return np.broadcast_to(flow.mean(axis=0), flow.shape)
    return rigid_flow(points, kabsch(points, points + flow))


class Collector:
    """Per-point and per-object records of every method over the dynamic foreground of the pairs seen."""

    def __init__(self, methods: list[str], crop: float | None, reference: str | None = None):
        self.methods, self.crop, self.reference = methods, crop, reference
        self.fit_errors = {name: [] for name in methods}  # against ``reference`` (the labels) instead of the truth
        self.fit_ratios = {name: [] for name in methods}
        self.points = {key: [] for key in ("classes", "object")}
        self.errors = {name: [] for name in methods}
        self.ratios = {name: [] for name in methods}
        self.mean_oracle = {name: [] for name in methods}
        self.rigid_oracle = {name: [] for name in methods}
        self.objects = []  # (speed m/s, extent m) per object, indexed by the per-point "object" ids
        self.seconds = {name: [] for name in methods}

    def add(self, pair, flows: dict[str, np.ndarray]) -> None:
        truth = PairTruth.of_pair(pair)
        dynamic = truth.paper(pair.dt, self.crop).masks["dynamic_fg"]
        if pair.instance is None:
            raise SystemExit(f"{pair.source}: the anatomy needs instance ids")
        ego = ego_flow(pair.pc0, pair.ego1_from_ego0)
        true_residual = truth.residual[dynamic]
        true_norm = np.maximum(np.linalg.norm(true_residual, axis=1), 1e-6)
        instances = pair.instance[dynamic]
        ids, object_of_point = np.unique(instances, return_inverse=True)
        first = len(self.objects)
        for k, instance in enumerate(ids):
            members = object_of_point == k
            speed = float(np.median(true_norm[members])) / pair.dt
            extent = object_extent(pair.pc0[pair.instance == instance])
            self.objects.append((speed, extent, int(members.sum())))
        self.points["classes"].append(pair.classes[dynamic])
        self.points["object"].append(first + object_of_point)
        gt = truth.gt_flow[dynamic]
        points = np.asarray(pair.pc0, np.float64)[dynamic]
        taught = None if self.reference is None else np.asarray(flows[self.reference], np.float64)[dynamic]
        taught_norm = None if taught is None else np.maximum(np.linalg.norm(taught - ego[dynamic], axis=1), 1e-6)
        for name in self.methods:
            flow = np.asarray(flows[name], np.float64)[dynamic]
            self.errors[name].append(np.linalg.norm(flow - gt, axis=1))
            residual = flow - ego[dynamic]
            self.ratios[name].append(np.linalg.norm(residual, axis=1) / true_norm)
            if taught is not None:
                self.fit_errors[name].append(np.linalg.norm(flow - taught, axis=1))
                self.fit_ratios[name].append(np.linalg.norm(residual, axis=1) / taught_norm)
            mean_flow, rigid_flow = np.empty_like(flow), np.empty_like(flow)
            for k in range(len(ids)):
                members = object_of_point == k
                mean_flow[members] = flow[members].mean(axis=0)
                rigid_flow[members] = rigid_oracle(points[members], flow[members])
            self.mean_oracle[name].append(np.linalg.norm(mean_flow - gt, axis=1))
            self.rigid_oracle[name].append(np.linalg.norm(rigid_flow - gt, axis=1))

    def report(self, class_names: dict[int, str]) -> str:
        classes = np.concatenate(self.points["classes"])
        objects = np.concatenate(self.points["object"])
        table = np.array(self.objects, dtype=np.float64).reshape(-1, 3)
        errors = {name: np.concatenate(values) for name, values in self.errors.items()}
        ratios = {name: np.concatenate(values) for name, values in self.ratios.items()}
        lines = [f"{len(classes)} dynamic-foreground points, {len(table)} moving objects"]
        names = " / ".join(self.methods)
        lines += ["", "Per class: share of dynamic points; EPE (m) per method; median speed ratio per method", ""]
        lines.append(f"| class | share | EPE: {names} | speed ratio: {names} |")
        lines.append("|---|---|" + "---|" * 2)
        for cls in [*np.unique(classes), None]:
            mask = np.ones(len(classes), bool) if cls is None else classes == cls
            label = "all dynamic" if cls is None else class_names.get(int(cls), str(cls))
            epe = " / ".join(f"{errors[n][mask].mean():.3f}" for n in self.methods)
            ratio = " / ".join(f"{np.median(ratios[n][mask]):.2f}" for n in self.methods)
            lines.append(f"| {label} | {mask.mean():.0%} | {epe} | {ratio} |")
        lines += ["", "Oracles (dynamic-foreground EPE, m): as predicted / each true object's mean / rigid fit", ""]
        lines.append("| method | as predicted | per-object mean | per-object rigid |")
        lines.append("|---|---|---|---|")
        for name in self.methods:
            mean = np.concatenate(self.mean_oracle[name]).mean()
            rigid = np.concatenate(self.rigid_oracle[name]).mean()
            lines.append(f"| {name} | {errors[name].mean():.3f} | {mean:.3f} | {rigid:.3f} |")
        for title, column, bins, unit in (
            ("true speed", 0, SPEED_BINS, "m/s"),
            ("extent along the main axis", 1, EXTENT_BINS, "m"),
        ):
            lines += ["", f"Per object by {title}: EPE (m) per method; median over objects of its speed ratio", ""]
            lines.append(f"| {title} ({unit}) | objects | share of points | EPE: {names} | speed ratio: {names} |")
            lines.append("|---|---|---|---|---|")
            for low, high in zip(bins[:-1], bins[1:]):
                chosen = np.flatnonzero(
                    (table[:, column] >= low) & (table[:, column] < high) & (table[:, 2] >= MIN_OBJECT_POINTS)
                )
                mask = np.isin(objects, chosen)
                if not mask.any():
                    continue
                epe = " / ".join(f"{errors[n][mask].mean():.3f}" for n in self.methods)
                per_object = {n: np.median([np.median(ratios[n][objects == k]) for k in chosen]) for n in self.methods}
                ratio = " / ".join(f"{per_object[n]:.2f}" for n in self.methods)
                lines.append(f"| {low:g}-{high:g} | {len(chosen)} | {mask.mean():.0%} | {epe} | {ratio} |")
        if self.reference is not None:
            fitted = [n for n in self.methods if n != self.reference]
            errors = {n: np.concatenate(self.fit_errors[n]) for n in fitted}
            ratios = {n: np.concatenate(self.fit_ratios[n]) for n in fitted}
            names = " / ".join(fitted)
            taught = self.reference
            lines += ["", f"The fit: against the {taught} instead of the truth, per class: EPE (m) per method;"]
            lines += [f"median speed ratio to the {taught}' residual motion per method", ""]
            lines.append(f"| class | EPE to the {taught}: {names} | speed ratio to the {taught}: {names} |")
            lines.append("|---|---|---|")
            for cls in [*np.unique(classes), None]:
                mask = np.ones(len(classes), bool) if cls is None else classes == cls
                label = "all dynamic" if cls is None else class_names.get(int(cls), str(cls))
                epe = " / ".join(f"{errors[n][mask].mean():.3f}" for n in fitted)
                ratio = " / ".join(f"{np.median(ratios[n][mask]):.2f}" for n in fitted)
                lines.append(f"| {label} | {epe} | {ratio} |")
        timing = [f"{n} {np.median(s) * 1e3:.0f} ms" for n, s in self.seconds.items() if s]
        if timing:
            lines += ["", "Median time per pair (whole call, ego motion and ground given): " + ", ".join(timing)]
        return "\n".join(lines)


def curve_points(run_dir: Path) -> dict[int, tuple[float | None, float | None, float]]:
    """{validation step: (mean training loss since the previous validation or None, validation loss or None,
    validation dynamic-foreground EPE)} of a training run's ``tensorboard/`` events."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = sorted(run_dir.glob("tensorboard/**/events.out.tfevents.*"))
    if not files:
        raise SystemExit(f"{run_dir}: no TensorBoard events under {run_dir / 'tensorboard'}")
    scalars = {}
    for file in files:  # a resumed run writes a version per launch; the later steps win
        events = EventAccumulator(str(file), size_guidance={"scalars": 0})
        events.Reload()
        for tag in ("train/loss", "val/loss", "val/dynamic_fg/EPE"):
            if tag in events.Tags()["scalars"]:
                scalars.setdefault(tag, {}).update({e.step: e.value for e in events.Scalars(tag)})
    train, points, previous = scalars.get("train/loss", {}), {}, -1
    for step in sorted(scalars.get("val/dynamic_fg/EPE", {})):
        window = [value for s, value in train.items() if previous < s <= step]
        mean = float(np.mean(window)) if window else None
        points[step] = (mean, scalars.get("val/loss", {}).get(step), scalars["val/dynamic_fg/EPE"][step])
        previous = step
    return points


def curves(run_dir: Path) -> str:
    """The training run's curves (:func:`curve_points`) as a table."""
    lines = [f"Curves of {run_dir}", ""]
    lines.append("| step | training loss (mean since the last validation) | val loss | val dynamic EPE (m) |")
    lines.append("|---|---|---|---|")
    for step, (mean, val_loss, val_epe) in curve_points(run_dir).items():
        lines.append(
            f"| {step} | {'-' if mean is None else f'{mean:.4f}'} | {'-' if val_loss is None else f'{val_loss:.4f}'} "
            f"| {val_epe:.4f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append", default=[], help="NAME=PATH: an export or checkpoint")
    parser.add_argument("--refine", action="append", default=[], help="NAME of a --model to also run refined")
    parser.add_argument("--teacher", action="store_true", help="score the dataset's teacher too")
    parser.add_argument("--cache", type=Path, help="npz of the teacher's flows (read, extended, written)")
    parser.add_argument("--set", action="append", default=[], help="an eval.py override (repeatable)")
    parser.add_argument("--labels", type=Path, help="label.py out_dir holding these pairs: the fit to the labels")
    parser.add_argument("--curves", type=Path, help="train.py out_dir: print its training and validation curves")
    args = parser.parse_args()
    if args.curves is not None:
        print(curves(args.curves), end="\n\n")
        if not args.model and not args.teacher and args.labels is None:
            return
    from fastflow3d.inference.predictor import Predictor
    from fastflow3d.inference.refine import RefineConfig

    overrides = args.set or ["split=test", "dataset.reader.num_sequences=16"]
    dataset, cfg = open_split(overrides)
    predictors = {}
    for item in args.model:
        name, _, path = item.partition("=")
        # float32 by name, as the recorded anatomies (the default, auto, would run an export's int8 network)
        predictors[name] = Predictor.load(path, precision="f32")
        if name in args.refine:
            predictors[f"{name}+refine"] = Predictor.load(path, precision="f32", refine=RefineConfig())
    teacher = teacher_flows(dataset, cfg, args.cache) if args.teacher else {}
    labels = None
    if args.labels is not None:
        from icpflow.evaluation.methods import ShardMethod

        labels = ShardMethod(args.labels)
    methods = ["ego", *(["teacher"] if args.teacher else []), *(["labels"] if labels else []), *predictors]
    collector = Collector(methods, cfg.crop, "labels" if labels else None)
    for index in range(len(dataset)):
        pair = dataset[index]
        flows = {"ego": ego_flow(pair.pc0, pair.ego1_from_ego0)}
        if args.teacher:
            flows["teacher"] = teacher[dataset.sample_id(index)]
        if labels is not None:
            flows["labels"] = labels(pair, index)
        for name, predictor in predictors.items():
            tic = time.perf_counter()
            flows[name] = predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1)
            collector.seconds[name].append(time.perf_counter() - tic)
        collector.add(pair, flows)
    class_names = {int(k): v for k, v in (dataset.class_to_meta or {}).items()}
    print(f"eval.py {' '.join(overrides)}: {len(dataset)} pairs")
    print(collector.report(class_names))


if __name__ == "__main__":
    main()
