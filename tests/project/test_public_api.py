"""The stable API (the release issue): ``from fastflow3d import Predictor, FlowStream, Prediction``; every module path
of the last release (the tree before issue 46's rooms, commit 4a28213) importable until 0.3 with a DeprecationWarning
naming today's path, its names today's objects; ``python -m fastflow3d.infer`` still runs the CLI; one meaning per
name (``FlowStream(refine_odometry=...)``, ``refine=`` its old name); ``Predictor.load``'s precision the CLI's
(default ``auto``, one of the CLI's choices, else refused) and its ``sensor_height`` refused as the CLI refuses it;
and every import of the python examples in README.md and docs/*.md runs."""

from __future__ import annotations

import ast
import importlib
import inspect
import re
import subprocess
import sys
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from helpers.data import REPO

FIXTURE_EXPORT = REPO / "tests" / "fixtures" / "release_0_1" / "export"


def _names(home: str, *names: str) -> dict[str, str]:
    """``{name: "home.name"}``: names that kept their name in their new module."""
    return {name: f"{home}.{name}" for name in names}


INFERENCE, ARTIFACT, NETWORK, TRAINING = (
    f"fastflow3d.{room}" for room in ("inference", "artifact", "network", "training")
)

#: old module -> (the module its warning names, {old name: today's object as "module.name"}): every public name the
#: old module defined that still exists. Left out, gone: fastflow3d.runtime.runtime_network (engines.load_network
#: opens every model file today).
MOVED_MODULES = {
    "fastflow3d.predictor": (
        f"{INFERENCE}.predictor",
        {
            **_names(f"{INFERENCE}.predictor", "Predictor"),
            **_names(f"{INFERENCE}.prediction", "Prediction", "PredictorError", "PredictorWarning", "as_points"),
            **_names(f"{INFERENCE}.model_loading", "checkpoint_contract", "given_contract"),
        },
    ),
    "fastflow3d.stream": (
        f"{INFERENCE}.stream",
        _names(f"{INFERENCE}.stream", "FlowStream", "StreamStep", "StreamWarning"),
    ),
    "fastflow3d.infer": (
        f"{INFERENCE}.cli",
        {
            **_names(
                f"{INFERENCE}.cli",
                "given_preprocessing",
                "infer",
                "infer_stream",
                "load_predictor",
                "main",
                "parse_args",
                "sensor_height",
            ),
            **_names(
                f"{INFERENCE}.scan_files",
                "NPZ_KEYS",
                "read_raw_scan",
                "read_transforms",
                "refuse_input_as_output",
                "write_flow",
            ),
            **_names(
                f"{INFERENCE}.stream_folder", "claim_output_folder", "read_manifest", "stream_files", "stream_manifest"
            ),
        },
    ),
    "fastflow3d.refine": (
        f"{INFERENCE}.refine",
        _names(f"{INFERENCE}.refine", "RefineConfig", "components", "refine_residual"),
    ),
    "fastflow3d.eval_method": (
        f"{INFERENCE}.eval_methods",
        _names(
            f"{INFERENCE}.eval_methods",
            "StreamedStudentMethod",
            "StudentMethod",
            "refined_streamed_student_method",
            "refined_student_method",
            "streamed_student_method",
            "student_method",
        ),
    ),
    "fastflow3d.runtime": (
        f"{ARTIFACT}.engines",
        {
            **_names(
                f"{ARTIFACT}.engines",
                "BF16_TOLERANCE",
                "PRECISIONS",
                "RUNTIMES",
                "OpenVinoNetwork",
                "cpu_only",
                "ort_session_options",
            ),
            "default_threads": "icpflow.core.threads.available_cores",
        },
    ),
    "fastflow3d.checkpoint": (
        f"{ARTIFACT}.checkpoint",
        _names(
            f"{ARTIFACT}.checkpoint",
            "MODEL_TARGET",
            "CheckpointError",
            "build_student",
            "load_student",
            "read_checkpoint",
        ),
    ),
    "fastflow3d.export": (
        f"{ARTIFACT}.export",
        _names(
            f"{ARTIFACT}.export",
            "CHECK_SIZES",
            "EXPECTED",
            "PARITY_TOLERANCE",
            "ExportError",
            "check_inputs",
            "check_replaceable",
            "default_export_dir",
            "export_checkpoint",
            "export_model",
            "measure_parity",
            "parse_formats",
            "quiet_exporters",
            "run_export",
        ),
    ),
    "fastflow3d.contract": (
        f"{NETWORK}.contract",
        _names(
            f"{NETWORK}.contract", "VERSION", "ContractError", "InputContract", "PreparedPair", "read_grid", "upgrade"
        ),
    ),
    "fastflow3d.model": (
        f"{NETWORK}.model",
        {
            **_names(
                f"{NETWORK}.model",
                "DECODERS",
                "NORMS",
                "ConvNormAct",
                "FastFlow3D",
                "GRUDecoder",
                "LinearDecoder",
                "PillarEmbedder",
                "UNet",
                "UpsampleSkip",
                "compensate",
                "encoder_stage",
                "local_correlation",
                "norm_layer",
                "split_linear",
            ),
            "pillar_rows": f"{NETWORK}.cells.image_rows",
        },
    ),
    "fastflow3d.scatter": (
        f"{NETWORK}.scatter",
        _names(f"{NETWORK}.scatter", "scatter_mean", "scatter_sum", "to_pseudo_image"),
    ),
    "fastflow3d.voxelize": (
        f"{NETWORK}.voxelize",
        _names(f"{NETWORK}.voxelize", "Grid", "pillar_centres", "pillar_ids", "voxelize"),
    ),
    "fastflow3d.augment": (
        f"{TRAINING}.augment",
        _names(
            f"{TRAINING}.augment",
            "FLOW_KEYS",
            "PER_POINT",
            "POINT_KEYS",
            "Augmentation",
            "subsample",
            "transform_sample",
        ),
    ),
    "fastflow3d.callbacks": (
        f"{TRAINING}.callbacks",
        _names(
            f"{TRAINING}.callbacks",
            "BEST_STATE_KEYS",
            "AtomicCheckpointIO",
            "LastCheckpoint",
            "ModelSize",
            "TrainingStopped",
            "ValidateAtEnd",
            "keep_best_after_resume",
            "log",
            "progress_bar",
            "set_best_checkpoints",
        ),
    ),
    "fastflow3d.data": (
        f"{TRAINING}.data",
        _names(
            f"{TRAINING}.data",
            "GT_KEYS",
            "PER_POINT0",
            "PER_POINT1",
            "DataError",
            "Draw",
            "EpochOrder",
            "NetworkCrop",
            "ShardDataModule",
            "StudentDataset",
            "collate",
            "init_worker",
            "labeller_contract",
            "split_samples",
        ),
    ),
    "fastflow3d.loss": (
        f"{TRAINING}.loss",
        _names(
            f"{TRAINING}.loss",
            "WEIGHTINGS",
            "flow_loss",
            "grouped_mean_sum",
            "object_loss",
            "speed_buckets",
            "speed_weight",
        ),
    ),
    "fastflow3d.options": (
        f"{TRAINING}.options",
        _names(
            f"{TRAINING}.options",
            "AugmentOptions",
            "DataOptions",
            "ExportOptions",
            "ExportStepOptions",
            "LossOptions",
            "MetricsOptions",
            "TrainOptions",
            "TrainerOptions",
            "register",
        ),
    ),
    "fastflow3d.schedules": (
        f"{TRAINING}.schedules",
        _names(f"{TRAINING}.schedules", "warmup_cosine", "warmup_multistep"),
    ),
    "fastflow3d.module": (
        f"{TRAINING}.student_module",
        _names(f"{TRAINING}.student_module", "LOSSES", "NonFiniteLoss", "StudentModule", "log"),
    ),
    "icpflow.entry": (
        "icpflow.core.errors_and_signals",
        _names(
            "icpflow.core.errors_and_signals",
            "FIXES",
            "FULL_ERROR",
            "MARKER",
            "STOP_SIGNALS",
            "Stop",
            "error_line",
            "exit_status",
            "launching_process",
            "on_signals",
            "one_line",
            "os_error_line",
            "raise_stop",
            "reported",
            "run",
            "signal_words",
            "signals_held",
            "stop_on_signals",
            "stop_signum",
        ),
    ),
    "icpflow.teacher.tracker": (
        "icpflow.teacher.long_horizon",
        _names(
            "icpflow.teacher.long_horizon",
            "HorizonResult",
            "SampleFlow",
            "long_horizon_flow",
            "sample_tracker_flow",
            "teacher_on_sample",
        ),
    ),
}

#: icpflow's modules before its rooms (release 0.2) -> (today's module, its names there); the options' names live in
#: two modules today
ICPFLOW_MOVED = {
    "icpflow.geometry": (
        "icpflow.core.geometry",
        (
            "ROTATION_ATOL ego_flow euler_angles full_to_residual invert is_rigid kabsch lengths "
            "make_transform orthonormalized pose_error relative_transform residual_to_full rigid_flow "
            "rigid_problem transform_points"
        ),
    ),
    "icpflow.frames": (
        "icpflow.core.frame_pair",
        "FramePair FramePairError FrameSequence MAX_ARRAY_VALUES MAX_POINTS MAX_POINT_COLUMNS check_points log",
    ),
    "icpflow.errors_and_signals": (
        "icpflow.core.errors_and_signals",
        (
            "FIXES FULL_ERROR MARKER STOP_SIGNALS Stop error_line exit_status launching_process "
            "on_signals one_line os_error_line raise_stop reported run signal_words signals_held "
            "stop_on_signals stop_signum"
        ),
    ),
    "icpflow.settings": (
        "icpflow.core.settings",
        (
            "HYDRA_KEYS OptionError RULES accepts broken_rule check_config check_target_arguments "
            "expand_home setting signature_schema store type_error_line type_words unknown_words"
        ),
    ),
    "icpflow.console": (
        "icpflow.core.console",
        (
            "ConsoleFormatter LIGHTNING_LOGGERS NOISE NOISE_WARNINGS NoiseFilter Progress "
            "ProgressSafeHandler WorkerHandler captured_output quiet recorded_warnings worker_logging"
        ),
    ),
    "icpflow.atomic": (
        "icpflow.core.atomic",
        "FolderInUse WriteError atomic_directory atomic_path folder_lock fsync_path temporary_name write_text_atomic",
    ),
    "icpflow.threads": ("icpflow.core.threads", "available_cores cpu_fields thread_limit"),
    "icpflow.hardware": (
        "icpflow.core.hardware",
        "BF16_FLAGS ISA_SWITCHES ONEDNN_ISAS cpu_flags host_line native_bf16 onednn_cap torch_bf16_flags",
    ),
    "icpflow.open3d_loader": ("icpflow.core.open3d_loader", "LIBUSB LIBUSB_FIX OPEN3D_FIX load_open3d provide_libusb"),
    "icpflow.deprecation": ("icpflow.core.deprecation", "REMOVAL moved_attribute moved_message warn_moved"),
    "icpflow.entry_points": (
        "icpflow.core.entry_points",
        "CHECKOUT_CONF CONFIG_PACKAGE config_path hydra_entry version_line",
    ),
    "icpflow.preprocess": (
        "icpflow.scans.preprocess",
        (
            "HeightFrame Preprocessing PreprocessingError estimate_ground_height implausible lift_points "
            "lift_pose lift_transform"
        ),
    ),
    "icpflow.ground": (
        "icpflow.scans.ground",
        "DROP_GRADE DROP_M FAR_SLACK FILL_REACH GroundSegmenter below_any_road ground_height object_columns",
    ),
    "icpflow.odometry": (
        "icpflow.scans.odometry",
        (
            "MIN_EGO_POINTS MIN_SPREAD Odometry OdometryStep TargetPlanes ego_settings "
            "estimate_ego_motion kiss_odometry normal_spread voxel_cloud"
        ),
    ),
    "icpflow.normals": ("icpflow.scans.normals", "plane_normals smallest_axes"),
    "icpflow.bev": ("icpflow.scans.bev", "in_box_cells occupied_cells"),
    "icpflow.teacher.neighbours": (
        "icpflow.scans.neighbours",
        "GAVE_UP MAX_KNN_SHELL build_grid k_nearest nearest nearest_distances nn_stats transform_cloud",
    ),
    "icpflow.metrics": (
        "icpflow.evaluation.metrics",
        (
            "AV2_CATEGORIES AV2_META BUCKET_EDGES Buckets CATEGORIES COLUMNS META_CLASSES "
            "MetricAccumulator PairTruth PaperSplits RELATIVE_EPS THREEWAY_EDGES THREEWAY_META "
            "av2_bucket_stats bucketed_epe format_table frame_pair_stats pair_stats threeway_epe"
        ),
    ),
    "icpflow.baselines": ("icpflow.evaluation.baselines", "ego_only_flow zero_flow"),
    "icpflow.viz_rerun": (
        "icpflow.viz.recording",
        "PairRecording SPEED_COLOURMAP VIEWERS ViewerUnavailable check_viewer import_rerun record_pair speed_colours",
    ),
    "icpflow.datasets.io": (
        "icpflow.datasets.file_formats",
        (
            "BIN_COLUMNS BIN_MAX_RANGE BIN_PLAUSIBLE_MEDIAN PLY_SIZES SCAN_SUFFIXES check_claim "
            "check_pcd_complete check_ply_complete fail list_scans load_npy load_npz natural_key read_bin "
            "read_feather read_pose_lines read_poses read_scan"
        ),
    ),
    "icpflow.datasets.sequence": ("icpflow.datasets.scan_folder", "ScanSequenceDataset"),
    "icpflow.synthetic.lidar": (
        "icpflow.datasets.synthetic.lidar",
        "ELEVATIONS EPS Lidar SENSOR_HEIGHT Scan cast intersect surface_distance",
    ),
    "icpflow.synthetic.scene": (
        "icpflow.datasets.synthetic.scene",
        (
            "AV2_META_CLASSES CLASSES CROSS_HALF Ground LANES PARKING RANGE_EDGE ROAD_HALF SIDEWALK Scene "
            "agent_shapes build_scene unicycle"
        ),
    ),
    "icpflow.synthetic.sequence": ("icpflow.datasets.synthetic.drive", "scan sequence"),
    "icpflow.teacher.registration_cpu": (
        "icpflow.teacher.registration.cpu",
        "grid_cell register_batch_cpu register_stages_cpu",
    ),
    "icpflow.teacher.registration_torch": ("icpflow.teacher.registration.torch_batch", "register_batch_torch"),
    "icpflow.teacher.icp": (
        "icpflow.teacher.registration.icp",
        "PLANE_MAX_ITER PLANE_NEIGHBOURS icp_point_to_plane icp_point_to_point normals",
    ),
}
#: the old package icpflow.synthetic's names (its modules': ICPFLOW_MOVED)
SYNTHETIC_NAMES = (
    "AV2_META_CLASSES",
    "CLASSES",
    "ELEVATIONS",
    "Lidar",
    "Scan",
    "Scene",
    "build_scene",
    "cast",
    "scan",
    "sequence",
)
MOVED_MODULES |= {old: (new, _names(new, *names.split())) for old, (new, names) in ICPFLOW_MOVED.items()}
MOVED_MODULES["icpflow.synthetic"] = (
    "icpflow.datasets.synthetic",
    _names("icpflow.datasets.synthetic", *SYNTHETIC_NAMES),
)
MOVED_MODULES["icpflow.options"] = (
    "icpflow.labelling.options",
    {
        **_names("icpflow.labelling.options", "DatasetOptions", "LabelOptions", "LabellerOptions", "RayOptions"),
        **_names("icpflow.labelling.options", "TeacherOverrides", "register"),
        **_names("icpflow.evaluation.options", "EvalOptions"),
    },
)

#: old modules that are packages today -> {old name: its module today}. Left out: fastflow3d.training.run_folder (the
#: old function; the name is today's module, whose function is fastflow3d.training.run_folder.run_folder).
MOVED_NAMES = {
    "fastflow3d.training": {
        **dict.fromkeys(
            (
                "log",
                "check_data",
                "training_contract",
                "build_module",
                "check_length",
                "export_formats",
                "build_trainer",
                "accumulation",
                "settle_batch",
                "best_checkpoint",
                "export_best",
                "check_sizes",
                "fit",
            ),
            f"{TRAINING}.trainer",
        ),
        **dict.fromkeys(
            (
                "TrainError",
                "resolve_ckpt_path",
                "kept_checkpoint",
                "check_fresh_start",
                "RESUME_FREE_DATA",
                "check_resume_settings",
            ),
            f"{TRAINING}.run_folder",
        ),
    },
    "fastflow3d.artifact": {
        **dict.fromkeys(
            (
                "FORMATS",
                "LEGACY_FORMATS",
                "FILE_NAMES",
                "LEGACY_FILE_NAMES",
                "SUFFIX_FORMATS",
                "METADATA_NAME",
                "METADATA_VERSION",
                "INPUT_NOTE",
                "INPUT_NAMES",
                "OUTPUT_NAMES",
                "FLOW_CONVENTION",
                "ArtifactError",
                "SingleSampleNet",
                "sha256_file",
                "grid_metadata",
                "network_metadata",
                "write_metadata",
                "read_metadata",
                "sibling_metadata",
                "listed_file",
            ),
            f"{ARTIFACT}.file_format",
        ),
        **dict.fromkeys(("write_onnx", "write_pt2", "WRITERS", "onnx_opset"), f"{ARTIFACT}.writers"),
        **dict.fromkeys(("OnnxRuntimeNetwork", "TorchNetwork", "choose_format", "load_network"), f"{ARTIFACT}.engines"),
        **dict.fromkeys(("TORCHSCRIPT_WARNING", "check_pt2"), f"{ARTIFACT}.safe_loading"),
    },
    "icpflow.viz": dict.fromkeys(
        ("RENDERER_BANNER", "flow_colours", "offscreen_problem", "plot_bev", "render_pair"), "icpflow.viz.pictures"
    ),
}


#: the message of an old path's warning (``icpflow.core.deprecation.moved_message``)
OURS = re.compile(r" is deprecated and will be removed in 0\.3; use ")


def resolve(dotted: str):
    """The object at ``module.name``."""
    module, _, name = dotted.rpartition(".")
    return getattr(importlib.import_module(module), name)


def fresh_import(name: str) -> tuple[object, list[warnings.WarningMessage]]:
    """The module ``name`` imported anew (its body run again) as an import statement of this file does, and the
    deprecations of ours that raised (a library imported for the first time may raise its own)."""
    sys.modules.pop(name, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DeprecationWarning)
        __import__(name)  # what an import statement calls: the frame above the import machinery is this one
    return sys.modules[name], [warning for warning in caught if OURS.search(str(warning.message))]


# ------------------------------------------------------------------------------------------------ the public names
def test_the_package_exports_the_predictor_the_stream_and_the_prediction():
    import fastflow3d
    from fastflow3d import FlowStream, Prediction, Predictor
    from fastflow3d.inference.prediction import Prediction as TodaysPrediction
    from fastflow3d.inference.predictor import Predictor as TodaysPredictor
    from fastflow3d.inference.stream import FlowStream as TodaysFlowStream

    assert (Predictor, FlowStream, Prediction) == (TodaysPredictor, TodaysFlowStream, TodaysPrediction)
    assert sorted(fastflow3d.__all__) == ["FlowStream", "Prediction", "Predictor"]
    with pytest.raises(AttributeError, match="has no attribute 'Predictr'"):
        fastflow3d.Predictr  # noqa: B018
    # icpflow's names as they were
    from icpflow import FramePair, ICPFlow, ICPFlowConfig  # noqa: F401


def test_importing_the_package_stays_cheap():
    """``import fastflow3d`` loads no heavy library: the exports are imported on first use."""
    code = "import sys, fastflow3d; print(' '.join(sorted(m for m in sys.modules if '.' not in m)))"
    loaded = set(subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True).stdout.split())
    assert "fastflow3d" in loaded and not loaded & {"torch", "numpy", "onnxruntime", "lightning", "hydra", "numba"}


# -------------------------------------------------------------------------------------- the last release's paths
@pytest.mark.parametrize("old", sorted(MOVED_MODULES))
def test_an_old_module_path_warns_once_and_gives_todays_objects(old):
    new, names = MOVED_MODULES[old]
    module, caught = fresh_import(old)
    assert len(caught) == 1 and issubclass(caught[0].category, DeprecationWarning)
    assert str(caught[0].message).startswith(f"{old} is deprecated and will be removed in 0.3; use {new}")
    assert caught[0].filename == __file__  # it points at the importer
    assert sorted(module.__all__) == sorted(names)
    for name, today in names.items():
        assert getattr(module, name) is resolve(today), f"{old}.{name}"
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        __import__(old)  # imported again: said once


def test_the_predictor_and_the_stream_point_at_the_package():
    for old, name in (("fastflow3d.predictor", "Predictor"), ("fastflow3d.stream", "FlowStream")):
        _, caught = fresh_import(old)
        assert str(caught[0].message).endswith(f"(or: from fastflow3d import {name})")


@pytest.mark.parametrize("package", sorted(MOVED_NAMES))
def test_an_old_module_that_is_a_package_today_answers_its_old_names(package):
    """``from fastflow3d.training import fit`` (the last release's module, a package today): today's object, with a
    DeprecationWarning naming its module (in the package's own room); a name it never had is an AttributeError."""
    module = importlib.import_module(package)
    assert module.MOVED == MOVED_NAMES[package]
    for name, home in MOVED_NAMES[package].items():
        assert home.startswith(f"{package}.")  # its own room: the package imports nothing outside it
        with pytest.warns(DeprecationWarning, match=re.escape(f"{package}.{name} is deprecated")) as caught:
            value = getattr(module, name)
        assert value is resolve(f"{home}.{name}")
        assert f"use {home}.{name}" in str(caught[0].message) and caught[0].filename == __file__
    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        module.no_such_name  # noqa: B018
    documented = {
        "fastflow3d.training": "build_trainer",
        "fastflow3d.artifact": "check_pt2",
        "icpflow.viz": "plot_bev",
    }[package]
    namespace = {}
    with pytest.warns(DeprecationWarning, match=re.escape(f"{package}.{documented} is deprecated")):
        exec(f"from {package} import {documented}", namespace)
    assert namespace[documented] is resolve(f"{MOVED_NAMES[package][documented]}.{documented}")


def test_a_name_of_the_old_training_module_that_is_a_module_today_is_the_module():
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        from fastflow3d.training import run_folder

    assert run_folder.__name__ == "fastflow3d.training.run_folder"


def test_the_old_targets_of_checkpoints_are_shims_of_the_same_modules():
    """A checkpoint's ``_target_`` of a moved module is read as today's path (``MOVED_TARGETS``), never through the
    shim; a config written by hand with the old path still imports, with the shim's warning naming the same module."""
    from fastflow3d.artifact.checkpoint import MOVED_TARGETS

    for old, new in MOVED_TARGETS.items():
        assert MOVED_MODULES[old][0] == new


def test_python_m_fastflow3d_infer_runs_the_cli_and_says_it_is_deprecated():
    result = subprocess.run(
        [sys.executable, "-m", "fastflow3d.infer", "--help"], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr
    assert "--precision" in result.stdout and "usage:" in result.stdout
    assert (
        "infer: warning: python -m fastflow3d.infer is deprecated and will be removed in 0.3; use fastflow3d-infer "
        "(or: python -m fastflow3d.inference.cli)"
    ) in result.stderr.splitlines()


# ----------------------------------------------------------------------------------------- one meaning per name
def _predictor_stub():
    """What a FlowStream reads of its Predictor when it is made: the ego-motion settings."""
    from icpflow.teacher.config import EgoMotionConfig

    return SimpleNamespace(ego_config=EgoMotionConfig())


def test_the_stream_refines_its_odometry_by_refine_odometry_and_refine_is_its_old_name():
    """``FlowStream(refine=...)`` (the Predictor's ``refine`` refines the flow) still means ``refine_odometry``, with
    a DeprecationWarning naming it: what a user runs gives the same results."""
    from fastflow3d.inference.stream import FlowStream

    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        assert FlowStream(_predictor_stub()).odometry.refine is True
        assert FlowStream(_predictor_stub(), refine_odometry=False).odometry.refine is False
        assert FlowStream(_predictor_stub(), 0.25, 0.5, 10, False).odometry.refine is False  # the old position
    for value in (False, True):
        with pytest.warns(DeprecationWarning, match=re.escape("use FlowStream(refine_odometry=...)")) as caught:
            stream = FlowStream(_predictor_stub(), refine=value)
        assert stream.odometry.refine is value and caught[0].filename == __file__
    assert "refine_odometry" in inspect.signature(FlowStream).parameters


# ------------------------------------------------------------------------------------ Predictor.load's arguments
def test_predictor_load_defaults_to_the_clis_precision_and_says_what_ran():
    from fastflow3d.inference.cli import parse_args
    from fastflow3d.inference.model_loading import AUTO, PRECISION_CHOICES
    from fastflow3d.inference.predictor import Predictor

    assert inspect.signature(Predictor.load).parameters["precision"].default == AUTO
    for choice in PRECISION_CHOICES:  # the CLI's --precision takes the same choices
        assert parse_args(["model.onnx", "a.npy", "b.npy", "--precision", choice]).precision == choice
    assert parse_args(["model.onnx", "a.npy", "b.npy"]).precision == AUTO
    # the previous release's export has no int8 network: auto runs float32, and says so
    assert Predictor.load(FIXTURE_EXPORT).precision == "f32"


@pytest.mark.parametrize("precision", ["INT8", "fp32", "float32", "", "Auto", None, 8, 32.0])
def test_predictor_load_refuses_a_precision_the_cli_refuses(precision, tmp_path):
    from fastflow3d.inference.predictor import Predictor

    with pytest.raises(ValueError, match=r"^precision=.*: use one of auto, f32, bf16, int8$"):
        Predictor.load(tmp_path / "missing", precision=precision)  # before the model is opened


@pytest.mark.parametrize("height", [-1, -0.01, float("nan"), float("inf"), 1e9, 100.5, True, "high", "1.73"])
def test_predictor_load_refuses_a_sensor_height_the_cli_refuses(height, tmp_path):
    from fastflow3d.inference.predictor import Predictor

    with pytest.raises(
        ValueError, match=r"^sensor_height=.* must be None, 'auto' or metres above the ground in \[0, 100\]$"
    ):
        Predictor.load(tmp_path / "missing", sensor_height=height)


#: options Predictor.load refuses before opening the model, as the CLI and eval.py do (one validation:
#: fastflow3d.inference.model_loading.check_load_options): option -> (bad values, the line's start)
BAD_LOAD_OPTIONS = {
    "threads": ([0, -2, True, 1.5, "2"], "threads="),
    "device": (["gpu", "cuda:99", "", 3], "device="),
    "runtime": (["tensorrt", "OpenVINO", 1], "runtime="),
    "precision": (["INT8", "fp32", None, 8, True], "precision="),
}


@pytest.mark.parametrize("option", sorted(BAD_LOAD_OPTIONS))
def test_predictor_load_checks_every_engine_option_before_the_model(option, tmp_path):
    from fastflow3d.inference.prediction import PredictorError
    from fastflow3d.inference.predictor import Predictor

    values, start = BAD_LOAD_OPTIONS[option]
    for value in values:
        with pytest.raises(PredictorError) as raised:
            Predictor.load(tmp_path / "missing", **{option: value})  # refused before the (missing) model is read
        assert str(raised.value).startswith(start) and "\n" not in str(raised.value), (option, value)
    assert Predictor.load(FIXTURE_EXPORT, threads=1, device="cpu", runtime="onnxruntime").precision


@pytest.mark.parametrize(
    "args, said",
    [
        (["--threads", "0"], "threads=0 must be a whole number >= 1"),
        (["--device", "gpu"], "device='gpu': not a torch device"),
        (["--sensor-height", "1730"], "'1730': must be 'auto' or metres above the ground in [0, 100]"),
        (["--sensor-height", "-1"], "'-1': must be 'auto' or metres above the ground in [0, 100]"),
    ],
)
def test_the_cli_refuses_the_engine_options_the_api_refuses(args, said, tmp_path, capsys):
    from fastflow3d.inference.cli import main as infer_main

    scans = []
    for name in ("a", "b"):
        np.save(tmp_path / f"{name}.npy", np.zeros((200, 3), np.float32))
        scans.append(str(tmp_path / f"{name}.npy"))
    try:
        status = infer_main([str(FIXTURE_EXPORT), *scans, "--out", str(tmp_path / "f.npz"), *args])
    except SystemExit as exit:  # argparse's own refusal of a --sensor-height value
        status = exit.code
    assert status == 2 and said in capsys.readouterr().err and not (tmp_path / "f.npz").exists()


def test_predictor_load_takes_the_heights_the_cli_takes():
    from fastflow3d.inference.predictor import Predictor

    for height in (None, "auto", 0, 1.73):
        assert Predictor.load(FIXTURE_EXPORT, sensor_height=height).sensor_height == height


# --------------------------------------------------------------------------------------- the docs' python imports
def doc_imports() -> list[tuple[str, str]]:
    """(page, statement) of every ``import X`` / ``from X import Y`` in the fenced python blocks of README.md and
    docs/*.md (a block that is not whole Python, e.g. with ``...`` lines, read line by line)."""
    found = []
    for page in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for block in re.findall(r"^```python\n(.*?)^```", page.read_text(), re.S | re.M):
            try:
                nodes = ast.walk(ast.parse(block))
            except SyntaxError:
                nodes = (node for line in block.splitlines() for node in _line_imports(line))
            for node in nodes:
                if isinstance(node, (ast.Import, ast.ImportFrom)):
                    found.append((page.name, ast.unparse(node)))
    return found


def _line_imports(line: str) -> list[ast.stmt]:
    try:
        return ast.parse(line.strip()).body if re.match(r"\s*(import|from)\s", line) else []
    except SyntaxError:
        return []


def test_every_import_of_the_docs_python_examples_runs():
    """Only the import statements run; none of them is an old path (a deprecation of ours is an error here)."""
    statements = doc_imports()
    assert any("Predictor" in statement for _, statement in statements)  # the check reads the README's examples
    for page, statement in statements:
        with warnings.catch_warnings():
            warnings.filterwarnings("error", message=f".*{OURS.pattern}", category=DeprecationWarning)
            exec(compile(statement, page, "exec"), {})
