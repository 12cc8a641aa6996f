"""The README's API tour runs as written."""
import re
from pathlib import Path


def test_readme_api_tour_runs():
    text = (Path(__file__).parent.parent / "README.md").read_text()
    block = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(block, "README.md", "exec"), namespace)
    best, ref, run = namespace["best"], namespace["ref"], namespace["run"]
    assert float(best.cost) == float(ref.cost)
    assert int(ref.nodes) == namespace["problem"].tree_size()
    assert run.states.shape == (81, 2)
