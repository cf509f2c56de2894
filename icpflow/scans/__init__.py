"""Steps on scans that the teacher and the student both take: the height frame and the preprocessing block
(``preprocess``), ground removal (``ground``), ego motion (``odometry``), exact nearest neighbours (``neighbours``),
plane normals (``normals``), bird's-eye-view cells (``bev``), and their settings blocks (``config``)."""
