"""The test suite as one package, so each test module has one name (mypy, pytest and `from tests.conftest import ...` agree)."""
