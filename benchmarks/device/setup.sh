# Sourced on the device machine (carry .devpkgs .gl .meshes; see pack.sh): unpacks the carried
# packages outside the image's own and sets the environment the benchmarks run in.
mkdir -p /tmp/site /tmp/gl
tar -C /tmp/site -xJf .devpkgs/site312.tar.xz
for f in .gl/*.deb; do dpkg -x "$f" /tmp/gl; done
# Neither plotly nor Mitsuba is there, and only the ray caster is used.
sed -i -E 's/^(from \.draw_plotly|from \.to_mitsuba)/pass  # &/' \
  /tmp/site/open3d/visualization/__init__.py
export LD_LIBRARY_PATH=/tmp/gl/usr/lib/x86_64-linux-gnu:/tmp/gl/lib/x86_64-linux-gnu
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
nvidia-smi -L
