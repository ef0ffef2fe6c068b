"""The example scripts run as written (issue 26 item 19: they use the public API and say true things).

``examples/signoff_notebook.py`` runs in tests/test_signoff.py (real recordings)."""

import runpy
from pathlib import Path

import numpy as np

EXAMPLES = Path(__file__).parents[1] / "examples"


def test_calibrate_from_python_recovers_the_simulated_truth(capsys):
    ns = runpy.run_path(str(EXAMPLES / "calibrate_from_python.py"), run_name="__main__")
    fit, truth, uq, test = ns["fit"], ns["truth_at_t0"], ns["uq"], ns["test"]
    # the printed truth is the simulator's: S + Ks T re-expressed about T0 (closed form, all three axes)
    z = (np.asarray(fit.theta) - truth) / np.asarray(fit.std)
    assert np.abs(z).max() < 4.0, z.round(1)                      # every parameter within 4 u of the truth
    rmse = np.sqrt(((test.b_ref - uq.mean) ** 2).mean(0))
    assert np.all(rmse < 0.08)                                    # 0.05 uT input noise through the model
    out = capsys.readouterr().out
    assert "truth" in out and "test RMSE (uT)" in out and "+- 0.00000" not in out


def test_examples_use_only_the_public_api():
    import ast
    import bayesmag
    for path in sorted(EXAMPLES.glob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [node.module or ""] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
                assert not any("_src" in n for n in names), f"{path.name}: imports {names}"
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in ("bm", "bayesmag"):
                assert node.attr in bayesmag.__all__, f"{path.name}: bayesmag.{node.attr} is not public"
