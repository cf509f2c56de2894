"""What several test modules share (tests/ is on sys.path: pytest's prepend import mode): the labelling runs of the
small synthetic world, hand-made shards, and small files in the PCAccumulation and ZeroFlow layouts."""
