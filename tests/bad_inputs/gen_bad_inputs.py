"""Generate the bad-input corpus of tests/bad_inputs (run: python3 gen_bad_inputs.py).

Each case is a model or scene directory that breaks exactly one invariant of DESIGN.md's
error rule; tests/bad_inputs.rs pins the error message of each. Written with pyarrow, so the
corpus also checks that files made by other tools are validated the same way. Deterministic:
no randomness, fixed values.
"""
import os
import shutil

import pyarrow as pa
import pyarrow.parquet as pq

HERE = os.path.dirname(os.path.abspath(__file__))
N = 4  # Gaussians
T = 3  # frames


def meta(table):
    return {b"usplat4d.table": table.encode(), b"usplat4d.schema_version": b"1"}


def gaussians_table():
    f32 = pa.float32()
    cols = {
        "gaussian_id": pa.array(range(N), pa.uint32()),
        "dynamic": pa.array([True] * N),
        "scale_x": pa.array([0.1] * N, f32),
        "scale_y": pa.array([0.1] * N, f32),
        "scale_z": pa.array([0.01] * N, f32),
        "opacity": pa.array([0.9] * N, f32),
        "r": pa.array([1.0] * N, f32),
        "g": pa.array([0.5] * N, f32),
        "b": pa.array([0.0] * N, f32),
        "sh_degree": pa.array([0] * N, pa.uint8()),
        "sh_rest": pa.array([[]] * N, pa.list_(pa.field("item", f32, nullable=False))),
    }
    schema = pa.schema([pa.field(k, v.type, nullable=False) for k, v in cols.items()], metadata=meta("gaussians"))
    return pa.table(list(cols.values()), schema=schema)


def frame_table(t, frame=None, x=None, quat=None):
    f32 = pa.float32()
    q = quat or [(1.0, 0.0, 0.0, 0.0)] * N
    cols = {
        "frame": pa.array([t if frame is None else frame] * N, pa.uint32()),
        "gaussian_id": pa.array(range(N), pa.uint32()),
        "x": pa.array(x or [float(t)] * N, f32),
        "y": pa.array([0.0] * N, f32),
        "z": pa.array([2.0] * N, f32),
        "qw": pa.array([v[0] for v in q], f32),
        "qx": pa.array([v[1] for v in q], f32),
        "qy": pa.array([v[2] for v in q], f32),
        "qz": pa.array([v[3] for v in q], f32),
    }
    schema = pa.schema([pa.field(k, v.type, nullable=False) for k, v in cols.items()], metadata=meta("trajectories"))
    return pa.table(list(cols.values()), schema=schema)


def write_model(name, frames):
    d = os.path.join(HERE, name)
    os.makedirs(d, exist_ok=True)
    pq.write_table(gaussians_table(), os.path.join(d, "gaussians.parquet"))
    with pq.ParquetWriter(os.path.join(d, "trajectories.parquet"), frames[0].schema) as w:
        for f in frames:  # one row group per frame
            w.write_table(f)
    return d


def main():
    for entry in os.listdir(HERE):
        p = os.path.join(HERE, entry)
        if os.path.isdir(p):
            shutil.rmtree(p)
    ok = [frame_table(t) for t in range(T)]
    write_model("model_nan_position", [ok[0], frame_table(1, x=[0.0, 0.0, float("nan"), 0.0]), ok[2]])
    write_model("model_frame_gap", [ok[0], frame_table(1, frame=2), ok[2]])
    write_model("model_zero_quaternion", [ok[0], ok[1], frame_table(2, quat=[(1, 0, 0, 0), (0, 0, 0, 0), (1, 0, 0, 0), (1, 0, 0, 0)])])
    d = write_model("model_truncated_gaussians", ok)
    g = os.path.join(d, "gaussians.parquet")
    data = open(g, "rb").read()
    open(g, "wb").write(data[: len(data) // 2])
    d = write_model("model_missing_column", ok)
    pq.write_table(gaussians_table().drop(["opacity"]), os.path.join(d, "gaussians.parquet"))


if __name__ == "__main__":
    main()
