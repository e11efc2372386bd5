#!/usr/bin/env bash
# Wheels that mjlab 1.6.0 needs on the GPU machine beyond its image (torch, numpy, scipy and
# pillow are there; mujoco, mujoco-warp and warp-lang come from ../shared/gpu/prepare-wheels),
# for Python 3.12, into .mjw/ (git-ignored): about 50 MB, one device call's carry.
#
#   benchmarks/mjlab_wheels.sh            # here, from the project root
#   then, on the GPU machine (carry [".mjw"]):
#   python3 -m pip install -q --no-index --no-deps --target /tmp/site2 .mjw/*.whl
#   PYTHONPATH=/tmp/site:/tmp/site2:$PWD benchmarks/gpu_mjlab.sh OUT
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
grep -qx '/.mjw/' .git/info/exclude 2>/dev/null || echo '/.mjw/' >> .git/info/exclude
rm -rf .mjw && mkdir .mjw
platform="--only-binary=:all: --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64
  --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64
  --platform manylinux1_x86_64 --platform any"
# shellcheck disable=SC2086
python3 -m pip download -q $platform -d .mjw viser mjviser tensorboard tyro prettytable mediapy trimesh GitPython \
  cloudpickle orjson pyvers importlib_metadata glfw
# shellcheck disable=SC2086
python3 -m pip download -q $platform --no-deps -d .mjw mjlab==1.6.0 tensordict==0.15.3 rsl-rl-lib==5.4.2
# on the image already, or carried apart (our pinned mujoco): two versions would stop the install
(cd .mjw && rm -f numpy-* mujoco-* mujoco_core-* mujoco_studio-* matplotlib-* fonttools-* contourpy-* kiwisolver-* \
  cycler-* pillow-* pyparsing-* python_dateutil-* setuptools-* psutil-* pyopengl-* PyOpenGL-*)
du -sh .mjw
