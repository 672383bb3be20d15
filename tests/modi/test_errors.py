"""Every user-facing error type is declared once, in ``modi.errors``; the modules that raise them re-export them
under the names users imported before."""
from __future__ import annotations

import importlib

import pytest

from modi import errors

OLD_PATHS = [
    ("modi.faults", "OutputError"), ("modi.faults", "RunFolderBusy"),
    ("modi.io.safe_load", "UnreadableFileError"), ("modi.io.safe_load", "UnsafeFileError"),
    ("modi.interop.modi_released", "MaskViolation"), ("modi.export.onnx", "OnnxExportError"),
    ("modi.models.modi.training", "NonFiniteLossError"), ("modi.models.ganimator.training", "NonFiniteLossError"),
    ("modi.models.modi", "NonFiniteLossError"),
]


@pytest.mark.parametrize("module,name", OLD_PATHS, ids=[f"{m}.{n}" for m, n in OLD_PATHS])
def test_old_import_paths_name_the_one_class(module, name):
    if module == "modi.export.onnx":
        pytest.importorskip("onnx")
    assert getattr(importlib.import_module(module), name) is getattr(errors, name)


@pytest.mark.parametrize("name", errors.__all__)
def test_each_is_a_user_error_defined_here(name):
    cls = getattr(errors, name)
    assert issubclass(cls, errors.UserError) and cls.__module__ == "modi.errors"


def test_non_finite_loss_is_one_line_exit_2_and_still_a_runtime_error():
    exc = errors.NonFiniteLossError("non-finite loss (d) at step 1")
    assert isinstance(exc, RuntimeError) and exc.exit_code == 2
