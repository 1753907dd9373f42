"""The snippets of the docs page "Using geofeat features in other code", run as written against the installed packages.

Each snippet is read out of ``docs/other_code.md`` (the fenced block after
``<!-- snippet: NAME -->``), so the page shows exactly the code tested here. pyFM
(``pyfmaps``) is installed; DiffusionNet (nmwsharp/diffusion-net) is not pip-installable, so
its snippet's features are fed to geofeat's own DiffusionNet, which takes the same (V, C_in)
input.
"""

from __future__ import annotations

import re

import numpy as np
import torch
from shapes import REPO

import geofeat

PAGE = REPO / "docs" / "other_code.md"


def page_snippet(name: str) -> str:
    """The Python block that follows ``<!-- snippet: name -->`` in docs/other_code.md."""
    text = PAGE.read_text(encoding="utf-8")
    found = re.search(rf"<!-- snippet: {re.escape(name)} -->\s*```python\n(.*?)```", text, flags=re.S)
    assert found is not None, f"{PAGE.relative_to(REPO)} has no snippet {name!r}"
    return found.group(1)


def test_snippets_are_on_the_page():
    for name in ("pyfm", "diffusionnet"):
        assert "geofeat.compute" in page_snippet(name)


def test_pyfm_snippet_gives_pyfm_own_wks_map(faust_dir, monkeypatch):
    """geofeat's WKS through pyFM's add_descriptors gives the map pyFM gives with its own WKS."""
    from pyFM.functional import FunctionalMapping

    monkeypatch.setenv("GEOFEAT_DATA", str(faust_dir.parent))
    ns: dict = {}
    exec(page_snippet("pyfm"), ns)
    model, mesh1 = ns["model"], ns["mesh1"]

    # pyFM with its own WKS on the same processed meshes (same eigenvectors, so the maps compare)
    own = FunctionalMapping(model.mesh1, model.mesh2)
    own.preprocess(n_descr=100, descr_type="WKS", k_process=200, k_descr=128)
    own.fit(K=(50, 50))
    p2p_own = own.get_p2p()

    for ours, theirs in ((model.descr1, own.descr1), (model.descr2, own.descr2)):
        assert ours.shape == theirs.shape == (ours.shape[0], 100)
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-5 * np.abs(theirs).max())
    np.testing.assert_allclose(model.FM_12, own.FM_12, rtol=0, atol=1e-3)
    assert (ns["p2p_21"] == p2p_own).mean() > 0.995

    # and the map is a good one: FAUST_r ground truth through the template points
    corr1 = np.loadtxt(faust_dir / "corres" / "tr_reg_080.vts", dtype=np.int64) - 1
    corr2 = np.loadtxt(faust_dir / "corres" / "tr_reg_081.vts", dtype=np.int64) - 1
    errors = {}
    for name, p2p in (("geofeat", ns["p2p_21"]), ("pyfm", p2p_own)):
        errors[name] = np.linalg.norm(mesh1.verts[p2p[corr2]] - mesh1.verts[corr1], axis=1).mean() / np.sqrt(mesh1.area())
    assert errors["geofeat"] < 0.05, errors  # a random map scores about 0.5
    assert abs(errors["geofeat"] - errors["pyfm"]) < 1e-3, errors


def test_diffusionnet_snippet_feeds_a_diffusionnet(faust_mesh):
    """The example's tensors in, geofeat features out, accepted by a DiffusionNet as its input."""
    from geofeat.adapters.blocks.diffusion_net import DiffusionNet
    from geofeat.adapters.blocks.operators import surface_operators

    verts = torch.tensor(faust_mesh.verts, dtype=torch.float32)  # what the example's dataset holds
    faces = torch.tensor(faust_mesh.faces)
    ns: dict = {"verts": verts, "faces": faces}
    exec(page_snippet("diffusionnet"), ns)
    features = ns["features"]
    assert isinstance(features, torch.Tensor) and features.shape == (faust_mesh.n_vertices, 128)
    float32_mesh = geofeat.Mesh(verts.double().numpy(), faces.numpy())
    expected = geofeat.compute(float32_mesh, "wks", n_descr=128)
    np.testing.assert_array_equal(features.numpy(), expected)

    torch.manual_seed(0)
    net = DiffusionNet(in_channels=features.shape[-1], out_channels=8, width=16, n_blocks=2)
    operators = surface_operators(float32_mesh, k=32)
    out = net(features, operators)
    assert out.shape == (faust_mesh.n_vertices, 8) and torch.isfinite(out).all()
    assert not torch.allclose(out, net(torch.zeros_like(features), operators))  # the input matters
