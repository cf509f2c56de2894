"""A trained network's files and how they are opened: training checkpoints (``checkpoint``), the export format
(``file_format``), its writers (``writers``), the check before a file is opened (``safe_loading``), the engines and
the one opener of a model file (``engines.load_network``), and the export with its parity check (``export``).
Imports ``fastflow3d.network`` only."""
