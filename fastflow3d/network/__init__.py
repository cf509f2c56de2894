"""The FastFlow3D network: the model (``model``), its pillars (``voxelize``, ``scatter``) and the input contract
(``contract``: what the network sees of two raw scans). Imports no other room of ``fastflow3d``."""
