"""Reference implementations the tests compare the package to."""
