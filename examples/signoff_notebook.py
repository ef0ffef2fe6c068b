# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # From the real recordings to a signed-off calibration
#
# The Belsten et al. (2023) recordings of a Honeywell HMC1053 AMR magnetometer against a MEDA
# FVM400 fluxgate, loaded with pandas, calibrated by a `bayesmag.run_job` from Python (the signed-off
# folder) and by `bayesmag.Calibrator` (the same fit, no files), the certificate's numbers and figures,
# and the PX4 parameters. A Jupyter notebook in jupytext's percent format
# (`jupytext --to notebook examples/signoff_notebook.py`), and a plain script:
# `python examples/signoff_notebook.py` (output in `$BAYESMAG_EXAMPLE_OUT`, default
# `runs/signoff_notebook`). `tests/test_signoff.py` runs it.

# %%
import json
import os
from pathlib import Path

import numpy as np
import pandas as pd

import bayesmag

out = Path(os.environ.get("BAYESMAG_EXAMPLE_OUT", "runs/signoff_notebook"))

# %% [markdown]
# ## The recordings, with pandas
#
# No header; columns `Time, refX, refY, refZ, testX, testY, testZ, Temp` (unix seconds, uT, K;
# the data folder's README). A gap of more than 5 s starts a new campaign (a run); the
# timestamps are whole seconds, so the rows inside one second are spread evenly over it.

# %%
path = bayesmag.find_dataset("belsten2023")            # $BAYESMAG_DATA_DIR or `bayesmag data fetch belsten2023`
raw = pd.read_csv(path, header=None, names=["t", "bx_ref", "by_ref", "bz_ref", "bx_meas", "by_meas", "bz_meas",
                                             "temperature"])
raw["run"] = (raw["t"].diff() > 5).cumsum() + 1
second = raw.groupby("t")
raw["time"] = raw["t"] - raw["t"].iloc[0] + second.cumcount() / second["t"].transform("size")
df = raw.drop(columns="t")
print(df.groupby("run").agg(rows=("time", "size"), T_min=("temperature", "min"), T_max=("temperature", "max")))

# %% [markdown]
# ## Fit
#
# Contiguous time blocks held out in every run (the random split leaks neighbours), T0 at the
# training mean, exact (analytic) uncertainty for the linear physics model; the certificate
# names the device and the reference.

# %%
config = {
    "name": "belsten_signoff",
    "split": {"kind": "time_blocks", "test_fraction": 0.1, "seed": 0},
    "physics": {"t0": "mean"},
    "uq": {"method": "analytic"},
    "certificate": {"dut": "Honeywell HMC1053 AMR (Belsten et al. 2023 recording)",
                    "reference": "MEDA FVM400 fluxgate, rotated into the DUT's axes"},
    "output": {"figures": True, "progress": False},
}
# The job reads its recording from a file (the run folder's certificate names it and its sha256):
# the pandas table, saved next to the run folder. (`bayesmag.Calibrator(config).fit(df)` fits the
# same calibration without files, for pipelines; the job writes the whole signed-off folder.)
out.parent.mkdir(parents=True, exist_ok=True)
csv = out.parent / f"{out.name}_recording.csv"
df.to_csv(csv, index=False)
config["data"] = {"path": str(csv), "temperature_unit": "K"}
result = bayesmag.run_job(bayesmag.config_from_dict(config), out)
run_dir = out
m = result["metrics"]

# %% [markdown]
# ## The same fit with `Calibrator`, without files
#
# The scikit-learn-style estimator fits the DataFrame directly (no CSV, no run folder): the same
# config, the same held-out rows (`holdout="config"`), hence the same parameters as the job's
# `params.json`; `cal.predict(new_df)` then calibrates a new recording with intervals.

# %%
cal = bayesmag.Calibrator({k: v for k, v in config.items() if k != "data"}, temperature_unit="K",
                          holdout="config").fit(df)
print(cal.params_[cal.params_["axis"] == "y"].to_string(index=False))
job_params = json.loads((run_dir / "params.json").read_text())["axes"]
largest = max(abs(r.value - job_params[r.axis]["values"][r.parameter]) for r in cal.params_.itertuples())
print(f"largest difference to the job's parameters: {largest:.1e}")

# %% [markdown]
# ## The certificate's numbers
#
# `report.md` / `report.html` in the run folder hold the whole certificate; here the numbers an
# engineer signs off on: accuracy, expanded uncertainty U for the same and a new session, and
# the field metrics (magnitude residual, heading error).

# %%
_, exported = bayesmag.export_run(run_dir, "json")     # calibration.export.json: coefficients, covariance, U
U = exported.uncertainty
rmse = m["physics"]["rmse"]
print("calibration ID", m["certificate"]["calibration_id"], "data sha256", m["certificate"]["data_sha256"][:16], "...")
print("test RMSE (uT)       " + "  ".join(f"{a}: {rmse[a]:.3g}" for a in "xyz"))
for key in ("same_session", "new_session"):
    print(f"U {key:13s} (uT) " + "  ".join(f"{a}: {U[key][a]['U']:.2g}" for a in "xyz"))
f = m["field"]["physics"]
print(f"heading error RMS {f['heading']['rms']:.3g} deg (max {f['heading']['max_abs']:.3g}) on "
      f"{f['heading']['n_rows']} rows; magnitude residual RMS {f['magnitude']['rms']:.3g} uT")

# %% [markdown]
# ## The certificate's figures

# %%
figures = sorted(p.name for p in run_dir.glob("*.png"))
try:                                                    # in a notebook: show them; as a script: list them
    get_ipython  # noqa: B018
    from IPython.display import Image, display
    for name in ("calibration.png", "physics_residuals_vs_time.png", "physics_calibration.png"):
        display(Image(filename=str(run_dir / name)))
except NameError:
    print("figures:", ", ".join(figures))

# %% [markdown]
# ## PX4 parameters
#
# `CAL_MAG0_*` and `TC_M0_*` (gauss), fitted to the physics model on the training rows; the
# accuracy lost is measured on the held-out rows. Set the device id placeholders before loading.

# %%
px4_file, px4 = bayesmag.export_run(run_dir, "px4")
print(px4_file)
print("\n".join(px4_file.read_text().splitlines()[-25:]))
lost = px4.accuracy["formats"]["px4"]["vs_reference"]
print("PX4 form, RMSE vs reference on the held-out rows (uT): " + "  ".join(f"{a}: {lost[a]:.3g}" for a in "xyz"))
