"""What several test modules share (tests/ is on sys.path: pytest's prepend import mode): the labelling runs of the
small synthetic world, hand-made shards, small files in the PCAccumulation and ZeroFlow layouts, the real samples in
../shared/data and the skip where one is absent (``data``), tiny trained students (``students``) and hand-built
teacher scenes (``teacher_scenes``)."""
