"""Fixtures shared by the whole test run: the Hypersim inputs of ``hypersim_inputs`` written once, and conversions of them."""

from pathlib import Path

import pytest

from tests.pipelines.hypersim.hypersim_inputs import Inputs, convert, write_inputs


@pytest.fixture(scope="session")
def inputs(tmp_path_factory) -> Inputs:
    return write_inputs(tmp_path_factory.mktemp("hypersim_hdf5"))


@pytest.fixture(scope="session")
def native(inputs, tmp_path_factory) -> Path:
    """Records at the rendered 64x48, lossless PNG so pixels can be checked exactly."""
    return convert(inputs, tmp_path_factory.mktemp("native") / "records", "--image-codec", "png")


@pytest.fixture(scope="session")
def half(inputs, tmp_path_factory) -> Path:
    return convert(inputs, tmp_path_factory.mktemp("half") / "records", "--resolution", "32x24", "--image-codec", "png")


@pytest.fixture(scope="session")
def exr_native(tmp_path_factory) -> Path:
    """The same scenes as renderer EXRs (+ label HDF5s), converted like ``native``."""
    exr_inputs = write_inputs(tmp_path_factory.mktemp("hypersim_exr"), exr=True)
    return convert(
        exr_inputs, tmp_path_factory.mktemp("exr") / "records", "--image-codec", "png", "--input-format", "exr"
    )
