"""Training recipes as data: params/recipes/<name>.yaml, ROS parameters files with a section per node.

`train`, the in-process trainer and the launch file read the same file, so a recipe's values live
in one place. A section's key names its node (`/**/sim_node`, `/**/trainer_node`,
`/**/policy_node`); its `ros__parameters` are that node's parameters.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import yaml

NODES = ("sim_node", "policy_node", "trainer_node")
DEFAULT_RECIPE = "shipped"


class RecipeError(ValueError):
    """A recipe that cannot be used; the message names the file and what is wrong."""


@dataclasses.dataclass(frozen=True)
class Recipe:
    path: Path
    params: dict[str, dict]  # node name -> its parameters

    def node(self, name: str) -> dict:
        return dict(self.params.get(name, {}))

    def ros_args(self, name: str) -> list[str]:
        """The node's recipe values as `-p NAME:=VALUE` arguments. Not `--params-file`: rcl ranks a file's
        node-named section above every `-p`, so the user's own `-p` after these could not override them."""
        return [x for k, v in self.params.get(name, {}).items() for x in ("-p", f"{k}:={ros_value(v)}")]

    def summary(self) -> str:
        """The recipe's parameters in one line, for logs."""
        return "; ".join(
            f"{node}: " + " ".join(f"{k}:={v}" for k, v in self.params[node].items()) for node in NODES if self.params.get(node)
        )


def recipe_path(name_or_file: str, params_dir: str | Path = "params") -> Path:
    """A recipe by name (params/recipes/<name>.yaml) or a path to the user's own file."""
    p = Path(name_or_file)
    if p.suffix in (".yaml", ".yml") or p.is_file():
        return p
    return Path(params_dir) / "recipes" / f"{name_or_file}.yaml"


def available(params_dir: str | Path = "params") -> list[str]:
    return sorted(p.stem for p in (Path(params_dir) / "recipes").glob("*.yaml"))


def load_recipe(name_or_file: str, params_dir: str | Path = "params") -> Recipe:
    """Read and check a recipe. RecipeError names the file and the problem (missing, unreadable, a section
    for no known node, a section without ros__parameters)."""
    path = recipe_path(name_or_file, params_dir)
    if not path.is_file():
        known = ", ".join(available(params_dir)) or "none found"
        raise RecipeError(f"recipe '{name_or_file}': no file {path} (recipes in {Path(params_dir) / 'recipes'}: {known})")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise RecipeError(f"recipe {path}: unreadable ({e})") from None
    if not isinstance(data, dict):
        raise RecipeError(f"recipe {path}: expected a mapping of node sections, got {type(data).__name__}")
    params: dict[str, dict] = {}
    for key, section in data.items():
        node = str(key).rsplit("/", 1)[-1]
        if node not in NODES:
            raise RecipeError(f"recipe {path}: section '{key}' names no node of the stack ({', '.join(NODES)})")
        values = section.get("ros__parameters") if isinstance(section, dict) else None
        if not isinstance(values, dict):
            raise RecipeError(f"recipe {path}: section '{key}' needs a 'ros__parameters' mapping")
        params[node] = values
    return Recipe(path, params)


def parse_assignments(items: list[str]) -> dict:
    """NAME:=VALUE pairs (as --ros-args -p takes them), values read as YAML; RecipeError for a malformed one."""
    out = {}
    for item in items:
        name, sep, value = item.partition(":=")
        if not sep or not name:
            raise RecipeError(f"'{item}' is not NAME:=VALUE")
        try:
            out[name] = yaml.safe_load(value)
        except yaml.YAMLError as e:
            raise RecipeError(f"'{item}': the value is not readable ({e})") from None
    return out


def ros_value(value) -> str:
    """A parameter value as `-p` takes it (YAML: true, 1.5, [1, 2], text)."""
    if isinstance(value, str):
        return value
    return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()
