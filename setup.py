"""The package list, which pyproject.toml cannot say: every package under src/, found (a new
one cannot be left out of the wheel; data folders such as the page's files come as namespace
packages), and the shipped configuration, which lives at the repository's top (config/),
where a reader looks for it, and goes in the wheel as the package
repetrel_host.shipped_config."""

from setuptools import find_namespace_packages, setup

setup(
    packages=[*find_namespace_packages("src"), "repetrel_host.shipped_config"],
    package_dir={"": "src", "repetrel_host.shipped_config": "config"},
)
