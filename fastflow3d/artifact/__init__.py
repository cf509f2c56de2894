"""A trained network's files and how they are opened: training checkpoints (``checkpoint``), the export format
(``file_format``), its writers (``writers``), the check before a file is opened (``safe_loading``), the engines and
the one opener of a model file (``engines.load_network``), and the export with its parity check (``export``).
Imports ``fastflow3d.network`` only."""

from icpflow.core.deprecation import moved_attribute

#: the names of the last release's module ``fastflow3d.artifact`` (this package since 0.2) -> their module today;
#: answered with a DeprecationWarning until 0.3 (``icpflow.core.deprecation``)
MOVED = {
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
        "fastflow3d.artifact.file_format",
    ),
    **dict.fromkeys(("write_onnx", "write_pt2", "WRITERS", "onnx_opset"), "fastflow3d.artifact.writers"),
    **dict.fromkeys(
        ("OnnxRuntimeNetwork", "TorchNetwork", "choose_format", "load_network"), "fastflow3d.artifact.engines"
    ),
    **dict.fromkeys(("TORCHSCRIPT_WARNING", "check_pt2"), "fastflow3d.artifact.safe_loading"),
}


def __getattr__(name: str):
    """A name of the last release's ``fastflow3d.artifact`` module (:data:`MOVED`), with a DeprecationWarning."""
    return moved_attribute(__name__, name, MOVED)
