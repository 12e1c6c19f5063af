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
    out = tmp_path / "render.pt"
    code = ("from b3dgs.render._ext import load_extension, cache_dir; m = load_extension(); "
            "print(cache_dir()); print(m.__file__); "
            f"from tests.test_build import render_and_grads; import torch; torch.save(render_and_grads(), {str(out)!r})")
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=900,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    build_dir = res.stdout.split()[0]
    ninja = open(os.path.join(build_dir, "build.ninja")).read()
    assert "cxx = clang++" in ninja  # really compiled by clang, not a cached GCC build
    assert res.stdout.split()[1].startswith(str(tmp_path))
    # clang's build (generic vector code, no instruction-set clones) computes what this process's build does
    import torch

    for a, b in zip(torch.load(out), render_and_grads()):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)


def render_and_grads():
    """A small render with weight sums and the gradients of every parameter (the kernels' code paths)."""
    from b3dgs.render.renderers import CPURenderer
    from tests.test_renderers import _camera, _params

    cam, p = _camera(), _params()
    out = CPURenderer().render(p, cam, sh_degree=3, return_weights=True)
    (out.rgb.square().sum() + out.alpha.sum() + out.depth.mean()).backward()
    return [out.rgb.detach(), out.weight_sum] + [p[k].grad for k in sorted(p)]
