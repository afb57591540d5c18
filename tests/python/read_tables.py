"""Read every Parquet file given on the command line with polars and with pandas, and print
one JSON object: {file: {"polars": {col: dtype}, "pandas": {col: dtype}, "values": {col: [...]},
"rows": n}}. The Rust interop test compares it with what it wrote."""
import json
import sys

import pandas as pd
import polars as pl


def plain(v):
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, float) and v != v:
        return None
    return v


out = {}
for path in sys.argv[1:]:
    df = pl.read_parquet(path)
    pdf = pd.read_parquet(path)
    assert len(df) == len(pdf), path
    assert list(df.columns) == list(pdf.columns), path
    out[path] = {
        "rows": len(df),
        "polars": {c: str(t) for c, t in zip(df.columns, df.dtypes)},
        "pandas": {c: str(t) for c, t in pdf.dtypes.items()},
        "values": {c: [plain(v) for v in df[c].to_list()] for c in df.columns},
        "pandas_values": {c: [plain(v) for v in pdf[c].tolist()] for c in pdf.columns},
    }
print(json.dumps(out))
