"""Parameter files given to a node process (`--ros-args --params-file FILE`) that must configure that node.

rcl applies a file's parameters only to the nodes its keys name and ignores the rest without
a word, so a misspelled node key (`plnat:`) would start the node on its defaults. This module
reads the files named in a process's arguments and refuses any that names no key matching
the node, with the rules rcl uses to match keys:

- nested keys are namespaces: `/ns: {plant: {ros__parameters: ...}}` names `/ns/plant`;
- a key without a leading slash is absolute: `plant` is `/plant`, never `/ns/plant`;
- a `*` token stands for exactly one name, a `**` token for any number of them (none too):
  `/**` configures every node, `/*/plant` a `plant` one namespace deep, `/**/plant` every `plant`.

By the same rules it tells which parameters the arguments give a node (`given_parameters`): rclpy
has no public view of a node's overrides, and a node checks them for names it never declared.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from ddarm.datafiles import PARAMETERS_KEY
from ddarm.datafiles import parameter_document as read_parameter_document
from ddarm.errors import DdarmError

ROS_ARGS, END_OF_ROS_ARGS, PARAMS_FILE = '--ros-args', '--', '--params-file'
PARAM_FLAGS = ('-p', '--param')
# rcl flags that take the next argument as their value (which is then not a flag of its own).
_FLAGS_WITH_VALUE = {'-r', '--remap', '-p', '--param', PARAMS_FILE, '-e', '--enclave', '--log-level',
                     '--log-config-file', '--log-file-name'}


class ParameterFileError(DdarmError, ValueError):
    """A parameter file that cannot configure the node; the text names the file."""


def _flag_values(arguments: Sequence[str]):
    """(flag, value) for each flag that takes a value in every `--ros-args` block (each ends at `--`), in order."""
    in_ros_args = False
    arguments = list(arguments)
    index = 0
    while index < len(arguments):
        argument = arguments[index]
        if not in_ros_args:
            in_ros_args = argument == ROS_ARGS
        elif argument == END_OF_ROS_ARGS:
            in_ros_args = False
        elif argument in _FLAGS_WITH_VALUE:
            if index + 1 < len(arguments):
                yield argument, arguments[index + 1]
            index += 1
        index += 1


def parameter_file_paths(arguments: Sequence[str]) -> list[str]:
    """The `--params-file` paths of every `--ros-args` block (each ends at `--`), in order."""
    return [value for flag, value in _flag_values(arguments) if flag == PARAMS_FILE]


def _join(namespace: str, key: str) -> str:
    return key if not namespace else namespace + ('' if namespace.endswith('/') else '/') + key


def _node_parameters(mapping: dict, namespace: str = '') -> list[tuple[str, object]]:
    """(node key, its `ros__parameters` mapping) for every node the document configures, namespaces joined."""
    nodes = []
    for key, value in mapping.items():
        if key == PARAMETERS_KEY:
            if namespace:
                nodes.append((namespace, value))
        elif isinstance(value, dict):
            nodes.extend(_node_parameters(value, _join(namespace, str(key))))
    return nodes


def parameter_document(path: str) -> dict:
    """The file's YAML (ddarm.datafiles.parameter_document), ParameterFileError naming what keeps it from being one."""
    return read_parameter_document(path, ParameterFileError)


def node_keys(path: str) -> list[str]:
    """The node names (as written, namespaces joined) whose `ros__parameters` the file holds."""
    document = parameter_document(path)
    keys = [key for key, _ in _node_parameters(document)]
    if not keys:
        raise ParameterFileError(f'parameter file {path} configures no node: no {PARAMETERS_KEY} under a node '
                                 f'name (its keys: {", ".join(str(key) for key in document) or "none"})')
    return keys


def _parameter_names(parameters, prefix: str = '') -> list[str]:
    """The parameter names of a `ros__parameters` mapping: nested mappings are dotted names, as rcl reads them."""
    if not isinstance(parameters, dict):
        return []
    names = []
    for key, value in parameters.items():
        if isinstance(value, dict):
            names.extend(_parameter_names(value, f'{prefix}{key}.'))
        else:
            names.append(f'{prefix}{key}')
    return names


def node_key_pattern(key: str) -> re.Pattern:
    """The fully qualified node names that a (possibly nested, possibly wildcard) node key configures."""
    absolute = key if key.startswith('/') else '/' + key
    parts = []
    for token in absolute.split('/')[1:]:
        if token == '**':
            parts.append(r'(?:/\w+)*')
        elif token == '*':
            parts.append(r'/\w+')
        else:
            parts.append('/' + re.escape(token))
    return re.compile(''.join(parts), re.ASCII)


def configures(key: str, fully_qualified_name: str) -> bool:
    return node_key_pattern(key).fullmatch(fully_qualified_name) is not None


def read_parameter_files(arguments: Sequence[str]) -> dict[str, list[str]]:
    """Each `--params-file` of the arguments with its node keys; refuses a file that configures no node."""
    return {path: node_keys(path) for path in parameter_file_paths(arguments)}


def given_parameters(arguments: Sequence[str], fully_qualified_name: str) -> list[str]:
    """The names of the parameters the arguments give the node `fully_qualified_name`, by rcl's rules.

    Each `--params-file`'s parameters under a node key that configures the node, and each
    `-p name:=value` (every node) or `-p node:name:=value` (the nodes `node` configures).
    """
    names = []
    for flag, value in _flag_values(arguments):
        if flag == PARAMS_FILE:
            for key, parameters in _node_parameters(parameter_document(value)):
                if configures(key, fully_qualified_name):
                    names.extend(_parameter_names(parameters))
        elif flag in PARAM_FLAGS:
            rule, assigned, _ = value.partition(':=')
            node, _, name = rule.rpartition(':')
            if assigned and (not node or configures(node, fully_qualified_name)):
                names.append(name)
    return list(dict.fromkeys(names))


def refuse_unconfigured(files: dict[str, list[str]], fully_qualified_name: str) -> None:
    """Refuse, naming it, the first file none of whose node keys configures `fully_qualified_name`."""
    for path, keys in files.items():
        if not any(configures(key, fully_qualified_name) for key in keys):
            raise ParameterFileError(f'{path} configures no node named {fully_qualified_name} '
                                     f'(its node keys: {", ".join(keys)})')


def check_parameter_files(arguments: Sequence[str], fully_qualified_name: str) -> None:
    """Refuse any parameter file of the process arguments that does not configure this node."""
    refuse_unconfigured(read_parameter_files(arguments), fully_qualified_name)
