"""The C++ extension builds with clang++ too (catches the next portability break, e.g. GCC 13's
``decltype(v[0])`` of a const vector being a const reference)."""
import os
import shutil
import subprocess
import sys

import pytest


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("clang++") is None, reason="clang++ not installed (apt-get install clang libomp-dev)")
def test_extension_builds_with_clang(tmp_path):
    env = dict(os.environ, CXX="clang++", B3DGS_CACHE=str(tmp_path))
    code = ("from b3dgs.render._ext import load_extension, cache_dir; m = load_extension(); "
            "print(cache_dir()); print(m.__file__)")
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    build_dir = res.stdout.split()[0]
    ninja = open(os.path.join(build_dir, "build.ninja")).read()
    assert "cxx = clang++" in ninja  # really compiled by clang, not a cached GCC build
    assert res.stdout.split()[1].startswith(str(tmp_path))
