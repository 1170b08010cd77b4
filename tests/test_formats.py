"""The one table of file formats: every reader and writer dispatches on it."""
import pytest

from implicit_scaffold.io import formats


@pytest.mark.parametrize("name, ext", [("a/B.NII.GZ", ".nii.gz"), ("scaffold.stl", ".stl"), ("x.Tiff", ".tiff"),
                                       ("noext", ""), ("dir.d/file.nrrd", ".nrrd"), ("a.gz", ".gz")])
def test_suffix_takes_nii_gz_whole_and_ignores_case(name, ext):
    assert formats.suffix(name) == ext


def test_match_names_only_the_listed_formats():
    assert formats.match("out.nii.gz", formats.FIELD_WRITERS) == ".nii.gz"
    assert formats.match("out.gz", formats.FIELD_WRITERS) is None
    assert formats.match("out.off", formats.MESH_WRITERS) is None  # read, not written
    assert formats.match("out.off", formats.MESH_READERS) == ".off"


def test_the_modules_dispatch_on_the_table():
    from implicit_scaffold.io import export, patient_io
    from implicit_scaffold.mesh import stream as mesh_stream, writers as mesh_writers
    from implicit_scaffold.measure import morphometry
    from implicit_scaffold import pipeline

    assert mesh_writers.MESH_FORMATS is formats.MESH_WRITERS is pipeline.MESH_FORMATS
    assert export.VOLUME_FORMATS is formats.FIELD_WRITERS is pipeline.FIELD_FORMATS
    assert mesh_stream.STREAM_FORMATS is formats.MESH_STREAMED
    assert set(formats.MESH_STREAMED) <= set(formats.MESH_WRITERS)
    assert patient_io.MESH_EXTENSIONS is formats.MESH_READERS is morphometry.MESH_SUFFIXES
    assert patient_io.VOLUME_EXTENSIONS is formats.VOLUME_READERS
    assert set(morphometry.VOLUME_SUFFIXES) == set(formats.VOLUME_READERS + formats.IMAGE_STACKS)


def test_the_cli_help_lists_every_format(capsys):
    from implicit_scaffold.cli import main

    with pytest.raises(SystemExit):
        main(["generate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for ext in formats.MESH_WRITERS + formats.FIELD_WRITERS + formats.MESH_READERS + formats.VOLUME_READERS:
        assert ext in text, ext
