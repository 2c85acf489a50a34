"""The importers' commands: help that names the docs section, output paths refused before any work."""
import pytest

from d2gs_np.cli import main

NEW_COMMANDS = ("import-colmap", "import-dyblurf", "export-trajectory")


def test_help_names_the_section_of_each_new_command(capsys):
    from test_docs_references import DOCS_REF, docs_index, find_dangling

    index = docs_index()
    assert main(["--help"]) == 0
    top = capsys.readouterr().out
    for cmd in NEW_COMMANDS:
        assert cmd in top
        assert main([cmd, "--help"]) == 0
        out = capsys.readouterr().out
        assert any(m.group(1) == "dataset_format.md" for m in DOCS_REF.finditer(out)), out
        assert not find_dangling(out, index), find_dangling(out, index)


@pytest.mark.parametrize("argv", [["import-colmap", "{d}", "{d}", "{f}"], ["import-dyblurf", "{d}", "{f}"]])
def test_an_output_path_that_is_a_file_is_refused(argv, tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    status = main([a.format(d=tmp_path, f=tmp_path / "file") for a in argv])
    err = capsys.readouterr().err
    assert status == 2 and "is a file" in err and err.count("\n") == 1
    assert (tmp_path / "file").read_text() == "x"
