"""Data files from someone else (motions, campaigns, the paper's settings, a bag's metadata.yaml), read within
stated bounds: a regular file of bounded size, UTF-8, and for a bag's metadata no YAML anchor or alias. The
lowest layer, so that every reader of such files (ddarm.motion, ddarm.recording, ddarm.tuning) shares one rule.
"""

from __future__ import annotations

import os
import stat
import struct
import sys
from pathlib import Path

import yaml
# What rosbags (pinned in setup.py) inflates MCAP chunks with, installed with it.
from lz4.frame import LZ4FrameDecompressor

if sys.version_info >= (3, 14):
    from compression import zstd
else:
    from backports import zstd

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
# What a bag's compressed MCAP chunks may inflate to, each and all together: rosbags inflates a chunk whole in
# memory before it compares the size its header states. An episode of a three-joint arm takes 0.5 kB a sample in
# a bag (all its topics), so 1 KiB for each of MAX_TOPIC_MESSAGES samples holds the longest episode's bag.
MAX_INFLATED_BYTES = MAX_TOPIC_MESSAGES * 2**10
# Top-level records of an MCAP storage file, each read to find the chunks: an episode's file has a few per chunk
# of 1 MiB, or one per message where it is not chunked (a few topics of MAX_TOPIC_MESSAGES messages); millions of
# tiny records would take minutes to walk, in this check and in rosbags.
MAX_MCAP_RECORDS = 8 * MAX_TOPIC_MESSAGES


class DataFileError(DdarmError, ValueError):
    """A data file that cannot be read at all: not a regular file, larger than its bound, or not UTF-8; or a bag's
    metadata.yaml that rosbag2 would never write."""


def unreachable(path: Path | str) -> OSError | None:
    """Why the OS cannot reach the input `path` (os.stat's OSError), or None when it can.

    Path.exists() is False for a symbolic-link loop (ELOOP), a folder that may not be searched (EACCES), a name
    too long (ENAMETOOLONG) or a file where a folder should be (ENOTDIR), as for nothing there: a check of an
    input that says "no such file" must say it for ENOENT alone (`is_missing`), and give any other refusal the
    OS's own reason (its strerror: 'Too many levels of symbolic links')."""
    try:
        os.stat(path)
    except OSError as error:
        return error
    return None


def is_missing(error: OSError | None) -> bool:
    """Whether `error` (unreachable's) says that nothing is there: ENOENT, no other reason."""
    return isinstance(error, FileNotFoundError)


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
    problem = regular_file_problem(status)
    if problem is not None:
        raise DataFileError(f'{path} {problem}')
    if status.st_size > limit:
        raise DataFileError(f'{path} holds {status.st_size} bytes, more than the {limit} it may')
    with path.open('rb') as file:
        data = file.read(status.st_size + 1)  # one byte more shows a file that grew since the stat
    if len(data) > status.st_size:
        raise DataFileError(f'{path} grew while it was read')
    return data


# What a path that is no regular file is, in the order stat tells them apart.
_NOT_REGULAR = ((stat.S_ISDIR, 'a directory'), (stat.S_ISFIFO, 'a FIFO'), (stat.S_ISSOCK, 'a socket'),
                (stat.S_ISCHR, 'a character device'), (stat.S_ISBLK, 'a block device'))


def regular_file_problem(status: os.stat_result) -> str | None:
    """What keeps a file of this status from being read as a data file ('is a FIFO, not a regular file': a FIFO
    or a device would block the read or never end it), or None for a regular file."""
    if stat.S_ISREG(status.st_mode):
        return None
    kind = next((name for test, name in _NOT_REGULAR if test(status.st_mode)), 'of no kind stat knows')
    return f'is {kind}, not a regular file'


# A ROS 2 parameter file: node names, each with its parameters under this key.
PARAMETERS_KEY = 'ros__parameters'
# Keys and items of one parameter file: a node of a thousand joints declares tens of thousands. Each value costs rcl
# and rclpy ~70 µs to hand to the node, so 3,000,000 (12 MB, within the file bound) kept a node starting for minutes.
MAX_PARAMETER_VALUES = 100_000


def parameter_document(path: str, error: type[Exception], what: str = 'parameter file') -> dict:
    """A ROS 2 parameter file's YAML, read within the bounds of read_data_file and MAX_PARAMETER_VALUES and, as
    rcl's parameter parser reads it, without anchors or aliases (a few hundred bytes of aliases expand to
    gigabytes); `error` (naming the file as `what`) for one that cannot be read, is not YAML or not a mapping."""
    try:
        text = read_data_file(path)
        problem = plain_yaml_problem(text, 'which no parameter file needs', MAX_PARAMETER_VALUES)
        document = yaml.load(text, Loader=SAFE_LOADER) if problem is None else None
    except (OSError, DataFileError) as failure:
        raise error(f'{what} {path} cannot be read: {failure}') from failure
    except yaml.YAMLError as failure:
        raise error(f'{what} {path} is not valid YAML: {" ".join(str(failure).split())}') from failure
    if problem is not None:
        raise error(f'{what} {path} {problem}')
    if not isinstance(document, dict):
        raise error(f'{what} {path} is not a mapping of node names to {PARAMETERS_KEY} (it holds '
                    f"{'nothing' if document is None else type(document).__name__})")
    return document


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
        if information.get('storage_identifier') == 'mcap':  # sqlite3 storage compresses nothing of its own
            _check_mcap_chunks(bag, name, status.st_size)


# The MCAP format (https://mcap.dev/spec), read here by hand, seeking past the data: rosbags' reader inflates each
# chunk it meets, and the mcap package is no dependency of ddarm's.
_MCAP_MAGIC = b'\x89MCAP0\r\n'
_RECORD = struct.Struct('<BQ')  # opcode, length of the record's content
_CHUNK, _CHUNK_INDEX = 0x06, 0x08
_SUMMARY_ENDS = (0x02, 0x0E)  # the footer, a summary offset: where rosbags stops reading chunk indexes
_CHUNK_HEAD = struct.Struct('<QQQII')  # message start and end times, uncompressed_size, its CRC; compression's length
_CHUNK_INDEX_HEAD = struct.Struct('<QQQQI')  # message times, chunk offset and length; message index offsets' length
_U64 = struct.Struct('<Q')
_FOOTER_BYTES = 37  # opcode, length, summary_start, summary_offset_start, CRC; the closing magic
_PIECE = 2**20  # of compressed data read, and of inflated data counted, at a time


def _check_mcap_chunks(bag: Path, name: str, size: int) -> None:
    """Refuse an MCAP file whose zstd or lz4 chunks inflate to more than MAX_INFLATED_BYTES, each or together, by
    the uncompressed_size their headers state or by what their data inflates to (rosbags inflates the data, and
    compares the size stated only after), or whose chunk index names data that is no such chunk. Nothing
    inflated is kept."""
    where = f'{bag}: storage file {name}'
    with open(bag / name, 'rb') as file:
        if size < len(_MCAP_MAGIC) + _FOOTER_BYTES or file.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
            return  # rosbags refuses it, saying why
        # rosbags walks the records from the start, inflating each chunk it meets, where the file has no index.
        chunks, total = {}, 0
        for offset, opcode in _mcap_records(file, len(_MCAP_MAGIC), size, where):
            if opcode != _CHUNK:
                continue
            head = file.read(_CHUNK_HEAD.size)
            if len(head) < _CHUNK_HEAD.size:
                break  # a truncated record, where rosbags fails too
            *_, declared, _, length = _CHUNK_HEAD.unpack(head)
            compression = file.read(length) if length <= 4 else b''  # rosbags refuses any but '', zstd and lz4
            if compression not in (b'zstd', b'lz4'):
                continue  # an uncompressed chunk is no larger than its part of the file
            total += declared
            chunk = f'{where}: the {compression.decode()} chunk at byte {offset}'
            if total > MAX_INFLATED_BYTES:
                raise DataFileError(f'{chunk} inflates to {declared} bytes (its uncompressed_size), the chunks to '
                                    f'{total} so far: more than the {MAX_INFLATED_BYTES} a bag may')
            (compressed,) = _U64.unpack(file.read(8).ljust(8, b'\0'))
            inflated = _inflated_size(file, compression, compressed, declared)
            if inflated > declared:
                raise DataFileError(f'{chunk} inflates to more than the {declared} bytes its uncompressed_size '
                                    'states')
            chunks[offset] = (compression, compressed)
        # Where the summary indexes the chunks, rosbags inflates the data each index names.
        file.seek(size - _FOOTER_BYTES + 9)
        (summary,) = _U64.unpack(file.read(8).ljust(8, b'\0'))
        indexed = set()
        for _, opcode in _mcap_records(file, summary, size, where) if summary else ():
            if opcode in _SUMMARY_ENDS:
                break
            head = file.read(_CHUNK_INDEX_HEAD.size) if opcode == _CHUNK_INDEX else b''
            if len(head) < _CHUNK_INDEX_HEAD.size:
                continue
            *_, offset, _, skipped = _CHUNK_INDEX_HEAD.unpack(head)
            file.seek(skipped + 8, os.SEEK_CUR)  # the message index offsets, and their length
            (length,) = struct.unpack('<I', file.read(4).ljust(4, b'\0'))
            compression = file.read(length) if length <= 4 else b''
            if compression not in (b'zstd', b'lz4'):
                continue
            (compressed,) = _U64.unpack(file.read(8).ljust(8, b'\0'))
            if chunks.get(offset) != (compression, compressed) or offset in indexed:
                raise DataFileError(f'{where}: a chunk index names {compressed} bytes of {compression.decode()} '
                                    f'data at byte {offset}, ' + ('a chunk indexed before' if offset in indexed
                                                                  else 'where no such chunk is'))
            indexed.add(offset)


def _mcap_records(file, offset: int, size: int, where: str):
    """(offset, opcode) of each record from `offset` on, the file at the record's content when one is yielded;
    DataFileError beyond MAX_MCAP_RECORDS of them."""
    for _ in range(MAX_MCAP_RECORDS):
        file.seek(offset)
        head = file.read(_RECORD.size)
        if len(head) < _RECORD.size:
            return
        opcode, length = _RECORD.unpack(head)
        yield offset, opcode
        offset += _RECORD.size + length
    raise DataFileError(f'{where} holds more than {MAX_MCAP_RECORDS} MCAP records, more than a bag of the longest '
                        'episode')


def _inflated_size(file, compression: bytes, compressed: int, limit: int) -> int:
    """The bytes that the `compressed` bytes at the file's position inflate to as rosbags inflates them (zstd
    frame after frame, lz4 its first frame only), counted to `limit` + 1 at most and not kept."""
    decompressor = zstd.ZstdDecompressor() if compression == b'zstd' else LZ4FrameDecompressor()
    inflated, data = 0, b''
    try:
        while inflated <= limit:
            if decompressor.eof:
                data += decompressor.unused_data
                if compression == b'lz4' or not (data or compressed):
                    break
                decompressor = zstd.ZstdDecompressor()
            elif decompressor.needs_input and not data:
                data = file.read(min(_PIECE, compressed))
                compressed -= len(data)
                if not data:
                    break  # the data ends before its frame: rosbags refuses it
            inflated += len(decompressor.decompress(data, max_length=_PIECE))
            data = b''
    except (zstd.ZstdError, RuntimeError):  # lz4 says RuntimeError
        pass  # damaged data, where rosbags' inflating stops too, refusing it
    return inflated
