"""Model files: npz + JSON, never pickle; clear errors for truncated or wrong files."""
import numpy as np
import pytest

from lacuna import modelfile
from lacuna.modelfile import ModelFileError
from mocap.baselines import HoldModel


@pytest.fixture
def saved(tmp_path, rng):
    m = HoldModel.fit([rng.normal(size=(20, 3))], ["a.rx", "b.rx", "c.rx"])
    p = tmp_path / "hold.npz"
    m.save(str(p))
    return p


def test_truncated_file_is_a_clear_error(saved, tmp_path):
    data = saved.read_bytes()
    for cut in (0, 10, len(data) // 2, len(data) - 5):
        bad = tmp_path / f"cut{cut}.npz"
        bad.write_bytes(data[:cut])
        with pytest.raises(ModelFileError, match=str(bad)):
            modelfile.load_model(str(bad))


def test_missing_file_wrong_format_version_and_nan(tmp_path, saved):
    with pytest.raises(ModelFileError, match="cannot read"):
        modelfile.load_model(str(tmp_path / "nope.npz"))
    meta, arrays = modelfile.load_arrays(str(saved))
    p = tmp_path / "v2.npz"
    modelfile.save_arrays(p, {**meta, "format_version": 2}, arrays)
    with pytest.raises(ModelFileError, match="format_version 2"):
        modelfile.load_model(str(p))
    arrays["mean"] = arrays["mean"].copy()
    arrays["mean"][0] = np.nan
    p = tmp_path / "nan.npz"
    modelfile.save_arrays(p, meta, arrays)
    with pytest.raises(ModelFileError, match="NaN"):
        modelfile.load_model(str(p))


def test_shape_mismatch_and_unknown_method(tmp_path, saved):
    meta, arrays = modelfile.load_arrays(str(saved))
    p = tmp_path / "shape.npz"
    modelfile.save_arrays(p, meta, {**arrays, "std": np.ones(7)})
    with pytest.raises(ModelFileError, match="'std' has shape"):
        modelfile.load_model(str(p))
    p = tmp_path / "m.npz"
    modelfile.save_arrays(p, {**meta, "method": "frobnicate"}, arrays)
    with pytest.raises(ModelFileError, match="unknown method 'frobnicate'"):
        modelfile.load_model(str(p))


def test_pickled_arrays_are_refused(tmp_path, saved):
    import io
    import json
    import zipfile

    p = tmp_path / "pickle.npz"
    buf = io.BytesIO()
    meta, arrays = modelfile.load_arrays(str(saved))
    np.savez(buf, __meta__=np.array(json.dumps(meta)), mean=np.array([{"x": 1}], dtype=object), std=arrays["std"])
    p.write_bytes(buf.getvalue())
    assert zipfile.is_zipfile(p)
    with pytest.raises(ModelFileError, match="not a readable model file"):
        modelfile.load_model(str(p))
    with pytest.raises(ValueError, match="object"):
        modelfile.save_arrays(tmp_path / "x.npz", meta, {"a": np.array([None], dtype=object)})
