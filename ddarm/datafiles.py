"""Data files from someone else (motions, campaigns, the paper's settings, a bag's metadata.yaml), read within
stated bounds: a regular file of bounded size, UTF-8, and for a bag's metadata no YAML anchor or alias. The
lowest layer, so that every reader of such files (ddarm.motion, ddarm.recording, ddarm.tuning) shares one rule.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import yaml

from ddarm.errors import DdarmError
from ddarm.samples import MAX_SAMPLES

# The bounds of a data file (a motion, a campaign, the paper's settings), each refused before the work it bounds.
# 32 MiB holds a motion of MAX_POINTS points of three joints' positions and velocities, written as repr writes them.
MAX_FILE_BYTES = 32 * 2**20
# Nesting levels: a data file nests a handful; each level is a frame of whatever walks the values.
MAX_DEPTH = 100
# libyaml's safe loader, where PyYAML was built with it: the pure-Python one took 56 ms per bag's metadata, a
# quarter of an episode's scoring.
SAFE_LOADER = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
# A bag's metadata.yaml: an episode's is a few kB (its topics, files and custom data); 1 MiB is thousands of topics.
MAX_METADATA_BYTES = 2**20
# Messages of one topic read from a bag, counted as they are read (the metadata's counts may lie): an episode's
# samples, one message each, and at most MAX_SAMPLES periods.
MAX_TOPIC_MESSAGES = MAX_SAMPLES + 1


class DataFileError(DdarmError, ValueError):
    """A data file that cannot be read at all: not a regular file, larger than its bound, or not UTF-8; or a bag's
    metadata.yaml that rosbag2 would never write."""


def read_data_file(path: Path | str, limit: int = MAX_FILE_BYTES) -> str:
    """The text of the data file at `path`, read only once it is known to be a regular file of at most `limit`
    bytes (a FIFO or a device would block or never end); OSError for what the OS refuses."""
    path = Path(path)
    data = read_data_bytes(path, limit)
    try:
        return data.decode('utf-8')
    except UnicodeDecodeError as error:
        raise DataFileError(f'{path} is not UTF-8 text ({error})') from None


def read_data_bytes(path: Path | str, limit: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of the file at `path`, as read_data_file reads them, not decoded."""
    path = Path(path)
    status = os.stat(path)
    if not stat.S_ISREG(status.st_mode):
        raise DataFileError(f'{path} is not a regular file')
    if status.st_size > limit:
        raise DataFileError(f'{path} holds {status.st_size} bytes, more than the {limit} it may')
    with path.open('rb') as file:
        data = file.read(status.st_size + 1)  # one byte more shows a file that grew since the stat
    if len(data) > status.st_size:
        raise DataFileError(f'{path} grew while it was read')
    return data


def plain_yaml_problem(text: str, reader: str, max_values: int | None = None) -> str | None:
    """What makes `text` more than plain YAML data (an anchor or alias, more than MAX_DEPTH levels, more than
    `max_values` scalars), said as `reader` ('which rosbag2 never writes') has it; None for plain data.
    yaml.YAMLError for YAML that is not."""
    depth = values = 0
    for event in yaml.parse(text, Loader=SAFE_LOADER):
        if isinstance(event, yaml.AliasEvent) or getattr(event, 'anchor', None) is not None:
            return f'holds a YAML anchor or alias, {reader}'
        if isinstance(event, yaml.ScalarEvent):
            values += 1
            if max_values is not None and values > max_values:
                return f'holds more than {max_values} values (keys and items), {reader}'
        elif isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_DEPTH:
                return f'nests more than {MAX_DEPTH} levels deep, {reader}'
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1
    return None


def bag_metadata_text(bag: Path | str) -> str:
    """The text of the bag's metadata.yaml, once it is known to be a regular file of at most MAX_METADATA_BYTES,
    nested at most MAX_DEPTH levels, with no YAML anchor or alias (rosbag2 writes none, and a few hundred bytes
    of aliases expand to gigabytes): checked before rosbags or anything else reads it. DataFileError naming the
    bag."""
    path = Path(bag)
    try:
        text = read_data_file(path / 'metadata.yaml', MAX_METADATA_BYTES)
        problem = plain_yaml_problem(text, 'which rosbag2 never writes')
    except (OSError, DataFileError, yaml.YAMLError) as error:
        raise DataFileError(f'{path}: unreadable bag: metadata.yaml: {" ".join(str(error).split())}') from error
    if problem is not None:
        raise DataFileError(f'{path}: metadata.yaml {problem}')
    _check_storage_files(path, yaml.load(text, Loader=SAFE_LOADER))
    return text


def _check_storage_files(bag: Path, metadata) -> None:
    """Refuse a compressed bag, and storage files named in the metadata that lie outside the bag's folder or are
    not regular files: reading a FIFO would wait for a writer for ever, a device would never end."""
    information = metadata.get('rosbag2_bagfile_information') if isinstance(metadata, dict) else None
    compression = information.get('compression_mode') if isinstance(information, dict) else None
    if compression:
        # rosbags inflates a file-compressed bag whole into the temporary folder before reading it, and a message
        # of a message-compressed one whole in memory: neither size is known before, so a small file can fill both.
        raise DataFileError(f'{bag}: metadata.yaml: compression_mode {compression!r} ('
                            f'{information.get("compression_format") or "no format"}): compressed bags are not read, '
                            'since their inflated size is unbounded until inflated; decompress it first (ros2 bag '
                            'convert, or rosbags-convert) and pass the copy')
    names = information.get('relative_file_paths') if isinstance(information, dict) else None
    if names is not None and not isinstance(names, list):
        raise DataFileError(f'{bag}: metadata.yaml: relative_file_paths is {type(names).__name__}, not a list of '
                            f'file names')
    for name in names or ():
        # rosbag2 writes plain names in the bag's folder, and rosbags opens the last part of whatever is there.
        if not isinstance(name, str) or not name or Path(name).name != name or name in ('.', '..'):
            raise DataFileError(f'{bag}: metadata.yaml: relative_file_paths entry {name!r} is not a file inside '
                                f'the bag')
        try:
            status = os.stat(bag / name)
        except OSError:
            continue  # a missing file is rosbags' to report, with what it knows of the storage
        if not stat.S_ISREG(status.st_mode):
            raise DataFileError(f'{bag}: storage file {name} is not a regular file (a FIFO, a socket or a '
                                f'device)')
