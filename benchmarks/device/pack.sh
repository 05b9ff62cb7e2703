#!/usr/bin/env bash
# Packs what `benchmarks/enhance.py --perf-child --device cuda` needs on the device machine
# (the device tool's image has Python 3.12, torch, numpy, scipy and OpenCV, not open3d,
# gpytoolbox or trimesh, and a call carries at most 64 MiB): cp312 wheels, open3d stripped
# of its TensorFlow/PyTorch ops and GUI resources (45 MB as xz), the GL/X11 libraries
# open3d links against as Debian packages, and the protocol meshes. Writes .devpkgs/, .gl/
# and .meshes/ (ignored via .git/info/exclude); then run benchmarks/device/run.sh there,
# carrying those three. Takes about 6 minutes (the xz).
set -euo pipefail
cd "$(dirname "$0")/../.."
for d in .devpkgs .gl .meshes; do
  grep -qx "/$d/" .git/info/exclude 2>/dev/null || echo "/$d/" >> .git/info/exclude
done
mkdir -p .devpkgs .gl .meshes
work=$(mktemp -d)
wheel() {
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_35_x86_64 --platform manylinux_2_31_x86_64 \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 -d "$work/whl" "$@"
}
wheel open3d-cpu==0.20.0 gpytoolbox==0.3.8 trimesh==5.2.0
mkdir "$work/site"
for w in "$work"/whl/*.whl; do unzip -q -o "$w" -d "$work/site"; done
rm -rf "$work"/site/open3d/{open3d_tf_ops.so,open3d_torch_ops.so,resources,examples} \
  "$work"/site/open3d/{labextension,nbextension,_ml3d,agent_skills} \
  "$work"/site/*.data "$work"/site/gpytoolbox_bindings_copyleft*
: > "$work/site/scs.py"  # gpytoolbox imports scs at start; the remesh never calls it
tar -C "$work/site" -cf - . | xz -9 -T0 > .devpkgs/site312.tar.xz
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists='"$work"/lists
mkdir -p "$work/lists/partial"
apt-get $o update -qq
(cd .gl && apt-get $o download -qq libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 \
  libx11-6 libx11-data libxcb1 libxau6 libxdmcp6 libbsd0 libmd0 libudev1 libusb-1.0-0 \
  libidn2-0 libunistring2)
cp ../shared/data/meshes/*.obj .meshes/  # every mesh: train.sh reads them all
rm -rf "$work"
du -sh .devpkgs .gl .meshes
