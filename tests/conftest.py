"""Tests run in float64 (x64 enabled here explicitly; the library never flips it).

``pytest --float32`` runs only the tests marked ``float32`` with x64 left off: the library's default
float32 path, on the exactness and budget properties (.ci/run runs both; README, "Tests")."""
import jax


def pytest_addoption(parser):
    parser.addoption("--float32", action="store_true",
                     help="run the tests marked float32, with x64 off (the library's default path)")


def pytest_configure(config):
    if not config.getoption("--float32"):
        jax.config.update("jax_enable_x64", True)


def pytest_collection_modifyitems(config, items):
    if config.getoption("--float32"):
        chosen = [item for item in items if item.get_closest_marker("float32")]
        config.hook.pytest_deselected(items=[item for item in items if item not in chosen])
        items[:] = chosen
