#!/usr/bin/env bash
# .wheels/open3d.tar.xz for a device run (benchmarks/gpu_run.py unpacks it): open3d-cpu's cp312 wheel is 99 MB,
# over what a device call carries (64 MiB with the checkout), and the stream's odometry needs open3d there. The
# archive holds the `open3d` package without its resources, examples and ML ops (the odometry uses its registration
# only) and `lib/`: the system libraries libOpen3D links beyond glibc and libstdc++, copied from this machine (the
# device image lacks the X, GL and USB ones). About 41 MB; xz takes about a minute on 2 cores.
#
#     bash benchmarks/pack_open3d.sh [open3d-cpu version, default 0.20.0]
set -euo pipefail
cd "$(dirname "$0")/.."
VERSION=${1:-0.20.0}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_35_x86_64 \
    -d "$WORK" "open3d-cpu==$VERSION"
mkdir -p "$WORK/pack/lib"
(cd "$WORK/pack" && unzip -q "$WORK"/open3d_cpu-*.whl 'open3d/*' -x 'open3d/resources/*' 'open3d/examples/*' \
    'open3d/_ml3d/*' 'open3d/open3d_tf_ops.so' 'open3d/open3d_torch_ops.so')
# open3d.visualization imports plotly (not on the device, 10 MB): its plotly functions are left out where it is absent
sed -i 's/^from \.draw_plotly import \(.*\)$/try:\n    from .draw_plotly import \1\nexcept ImportError:\n    pass/' \
    "$WORK/pack/open3d/visualization/__init__.py"
for name in libEGL.so.1 libGL.so.1 libGLX.so.0 libGLdispatch.so.0 libX11.so.6 libXau.so.6 libXdmcp.so.6 libxcb.so.1 \
    libbsd.so.0 libmd.so.0 libidn2.so.0 libunistring.so.2 libudev.so.1 libusb-1.0.so.0; do
    path=$(ldconfig -p | awk -v name="$name" '$1 == name && !found {print $NF; found = 1}')
    [ -n "$path" ] || { echo "pack_open3d: $name is not on this machine (apt-get install the package holding it)" >&2; exit 1; }
    cp -L "$path" "$WORK/pack/lib/"
done
mkdir -p .wheels
tar -C "$WORK/pack" -cf - open3d lib | xz -T0 -6 > .wheels/open3d.tar.xz.part
mv .wheels/open3d.tar.xz.part .wheels/open3d.tar.xz
ls -l .wheels/open3d.tar.xz
