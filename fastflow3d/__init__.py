"""fastflow3d: the FastFlow3D student network, its training on pseudo-flow shards, and export."""
