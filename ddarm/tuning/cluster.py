"""Independent jobs (ddarm.tuning.jobs.Job) as Ray tasks on an existing Ray cluster, with the results run_jobs gives.

Ray is an optional extra (`pip install 'ddarm[ray]'`), imported only here and only when a cluster is asked for.
Each job runs as one task on one CPU; its function is a pure function of its arguments (a search and its seed), so
its result is bit for bit the one it has in this process, provided every node runs the same code: before any job
is sent, one task on each node with CPUs reports a fingerprint of its ddarm sources and numerical libraries, and a
node that differs from this process is refused.

Ray has no authentication: anyone who can reach a cluster's ports can run any code on it. Start clusters bound to
127.0.0.1 or to a trusted private network only (docs/tuning.md, `ddarm campaign`).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import ipaddress
import logging
import os
import platform
import socket
import time
from pathlib import Path

from ddarm.errors import DdarmError
from ddarm.interrupts import check_stop
from ddarm.tuning.jobs import POLL_S, Job, JobError

RAY_EXTRA = "pip install 'ddarm[ray]'"
# The libraries whose versions decide a search's numbers, beside ddarm's own sources.
NUMERICAL_PACKAGES = ('numpy', 'numba', 'scipy', 'cma', 'pin')
CPUS_PER_JOB = 1
# How long the address may take to accept a connection, and then to answer as a Ray cluster's GCS, before it is
# refused: ray.init itself retries for a quarter of an hour against a port where something else listens.
CONNECT_TIMEOUT_S = 5.0
# Ray replaces a loopback address by the machine's outward address (to reach multi-node clusters) unless this is 0,
# Ray's switch for a one-machine cluster; a cluster started with it set listens on 127.0.0.1 only.
LOOPBACK_SWITCH = 'RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER'


class ClusterError(DdarmError, RuntimeError):
    """A Ray cluster that cannot run the jobs: Ray missing, no cluster at the address, a node with other code."""


def cluster_address(address: str) -> tuple[str, int]:
    """The host and port of a Ray cluster's address (`ray start --head --port`'s), `host:port`."""
    host, colon, port = address.rpartition(':')
    host = host.strip('[]')  # an IPv6 host in brackets
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ClusterError(f'--ray {address!r}: give the cluster\'s address as host:port (the head node\'s GCS port, '
                           'ray start --head --port=PORT)')
    return host, int(port)


def is_loopback(host: str) -> bool:
    try:
        return host == 'localhost' or ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


# gRPC over HTTP/2 without TLS (RFC 9113, gRPC's PROTOCOL-HTTP2.md): what a Ray GCS speaks, just enough to make one
# unary call and see whether a reply comes. Frame types and flags:
_DATA, _HEADERS, _RST_STREAM, _SETTINGS, _GOAWAY = 0x0, 0x1, 0x3, 0x4, 0x7
_END_STREAM, _ACK, _END_HEADERS = 0x1, 0x1, 0x4
_PREFACE = b'PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n'
# The call ray.init opens with: NodeInfoGcsService.GetClusterId, its request empty.
_PROBE_PATH = '/ray.rpc.NodeInfoGcsService/GetClusterId'


def _frame(kind: int, flags: int, stream: int, payload: bytes = b'') -> bytes:
    return len(payload).to_bytes(3, 'big') + bytes([kind, flags]) + stream.to_bytes(4, 'big') + payload


def _literal_header(name: str, value: str) -> bytes:
    # HPACK's literal header field without indexing, new name, no Huffman coding (RFC 7541 §6.2.2): each string
    # under 127 bytes, so its length is one byte.
    return b'\x00' + bytes([len(name)]) + name.encode() + bytes([len(value)]) + value.encode()


def _gcs_probe(host: str, port: int) -> bytes:
    headers = b''.join(_literal_header(name, value) for name, value in (
        (':method', 'POST'), (':scheme', 'http'), (':path', _PROBE_PATH), (':authority', f'{host}:{port}'),
        ('content-type', 'application/grpc'), ('te', 'trailers')))
    return (_PREFACE + _frame(_SETTINGS, 0, 0) + _frame(_HEADERS, _END_HEADERS, 1, headers)
            + _frame(_DATA, _END_STREAM, 1, b'\x00' + (0).to_bytes(4, 'big')))  # one uncompressed, empty message


def _answers_as_gcs(host: str, port: int) -> bool:
    """Whether the peer answers the GCS's GetClusterId with a reply message within CONNECT_TIMEOUT_S: a Ray GCS
    does; a gRPC server of another service ends the call without one, anything else never answers in HTTP/2."""
    deadline = time.monotonic() + CONNECT_TIMEOUT_S
    with socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S) as connection:
        connection.sendall(_gcs_probe(host, port))
        received = b''

        def read(count: int) -> bytes:
            nonlocal received
            while len(received) < count:
                left = deadline - time.monotonic()
                if left <= 0:  # also against a peer that never stops sending
                    raise TimeoutError
                connection.settimeout(left)
                chunk = connection.recv(65536)
                if not chunk:
                    raise ConnectionError('the connection was closed')
                received += chunk
            taken, received = received[:count], received[count:]
            return taken

        while True:
            header = read(9)
            length, kind, flags = int.from_bytes(header[:3], 'big'), header[3], header[4]
            stream = int.from_bytes(header[5:], 'big') & 0x7FFFFFFF
            if length > 2**14:  # above HTTP/2's initial largest frame: no HTTP/2 server sends it unasked
                return False
            read(length)
            if kind == _SETTINGS and not flags & _ACK:
                connection.sendall(_frame(_SETTINGS, _ACK, 0))
            elif stream == 1 and kind == _DATA:
                return True
            elif kind == _GOAWAY or stream == 1 and (kind == _RST_STREAM or kind == _HEADERS and flags & _END_STREAM):
                return False  # the call ended without a reply


def _check_gcs(address: str, host: str, port: int) -> None:
    """Refuse an address where something listens that is not a Ray cluster's GCS: ray.init would wait there."""
    try:
        answered, why = _answers_as_gcs(host, port), ''
    except TimeoutError:
        answered, why = False, f' (no answer within {CONNECT_TIMEOUT_S:g} s)'
    except OSError as error:  # the connection closed or reset
        answered, why = False, f' ({error})'
    if not answered:
        raise ClusterError(f'--ray {address}: something listens there, but it does not answer as a Ray cluster\'s '
                           f'GCS{why}; give the head node\'s GCS port (ray start --head --port=PORT)')


def code_fingerprint() -> dict:
    """What a job's numbers depend on besides its arguments: ddarm's sources (a hash), Python's and the numerical
    libraries' versions."""
    package = Path(__file__).resolve().parents[1]  # ddarm/
    digest = hashlib.sha256()
    for path in sorted(package.rglob('*.py')):
        digest.update(path.relative_to(package).as_posix().encode() + b'\0' + path.read_bytes() + b'\0')
    return {'ddarm_sources': digest.hexdigest(), 'python': platform.python_version(),
            **{name: importlib.metadata.version(name) for name in NUMERICAL_PACKAGES}}


def _run_job(function, arguments: tuple):
    """A job in a Ray worker, on the one CPU its task holds."""
    from ddarm.episodes.engine import set_default_threads

    set_default_threads(CPUS_PER_JOB)
    return function(*arguments, progress=None)


class RayCluster:
    """A connection to the Ray cluster at `address` (`ray.init(address=...)`), its nodes' code checked; closed on
    leaving the block."""

    def __init__(self, address: str) -> None:
        host, port = cluster_address(address)
        if importlib.util.find_spec('ray') is None:
            raise ClusterError(f'--ray needs Ray, which is not installed: {RAY_EXTRA}')
        try:
            socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S).close()
        except OSError as error:
            raise ClusterError(f'--ray {address}: no Ray cluster answers there ({error}); start one with ray start '
                               '--head (docs/tuning.md: `ddarm campaign`)') from error
        loopback = is_loopback(host)
        if loopback:
            os.environ.setdefault(LOOPBACK_SWITCH, '0')  # read when ray is imported
        import ray
        from ray._private import ray_constants

        if loopback and ray_constants.ENABLE_RAY_CLUSTER:
            # Imported before the switch was set: ray.init would wait for ever on the machine's outward address.
            raise ClusterError(f'--ray {address}: Ray was imported in this process before ddarm could set '
                               f'{LOOPBACK_SWITCH}=0, without which it does not connect to a cluster on 127.0.0.1; '
                               f'set it in the environment')

        _check_gcs(address, host, port)
        self.ray, self.address = ray, address
        try:
            # Workers' output is not forwarded: this process's stdout may be JSON (--json), and a job's failure
            # comes back with its traceback through ray.get.
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
        except (ConnectionError, RuntimeError, ValueError) as error:
            raise ClusterError(f'--ray {address}: cannot connect to a Ray cluster there: {error}') from error
        try:
            self._check_nodes()
        except BaseException:
            self.close()
            raise

    def _check_nodes(self) -> None:
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        ray = self.ray
        nodes = [node for node in ray.nodes() if node['Alive'] and node['Resources'].get('CPU', 0) >= CPUS_PER_JOB]
        if not nodes:
            raise ClusterError(f'--ray {self.address}: the cluster has no node with a CPU to run jobs on')
        fingerprint = ray.remote(code_fingerprint)
        ours = code_fingerprint()
        theirs = ray.get([fingerprint.options(num_cpus=0, scheduling_strategy=NodeAffinitySchedulingStrategy(
            node['NodeID'], soft=False)).remote() for node in nodes])
        for node, fingerprint in zip(nodes, theirs):
            different = {key: (ours[key], fingerprint.get(key)) for key in ours if fingerprint.get(key) != ours[key]}
            if different:
                raise ClusterError(
                    f"--ray {self.address}: the node {node['NodeManagerAddress']} runs other code than this process "
                    f"({'; '.join(f'{key}: {mine} here, {other} there' for key, (mine, other) in different.items())}): "
                    'install the same ddarm and libraries on every node, or its results would not be those of a '
                    'local run')

    def run_jobs(self, jobs: list[Job], *, on_done=None, check=check_stop) -> dict:
        """Every job's result by key, as ddarm.tuning.jobs.run_jobs gives them; `on_done(job, result)` as each
        ends. Jobs that need others' results are not taken. A job's exception is raised here; so is what `check`
        raises (called at least every POLL_S s), after the tasks not done are cancelled."""
        ray = self.ray
        needing = [job.label for job in jobs if job.needs]
        if needing:
            raise JobError(f'jobs that need other jobs\' results do not run as Ray tasks: {needing}')
        on_done = on_done or (lambda job, result: None)
        task = ray.remote(_run_job).options(num_cpus=CPUS_PER_JOB)
        by_reference = {task.remote(job.function, job.arguments): job for job in jobs}
        results, pending = {}, list(by_reference)
        try:
            while pending:
                check()
                done, pending = ray.wait(pending, num_returns=1, timeout=POLL_S)
                for reference in done:
                    job = by_reference[reference]
                    try:
                        results[job.key] = ray.get(reference)
                    except ray.exceptions.RayTaskError as error:  # the job's own exception, its traceback noted
                        cause = error.as_instanceof_cause()
                        cause.add_note(f'in the job {job.label!r}, as a Ray task')
                        raise cause from None
                    except ray.exceptions.RayError as error:  # the task's worker or node failed, not the job
                        raise JobError(f'{job.label}: its Ray task failed: {error}') from error
                    on_done(job, results[job.key])
        finally:
            for reference in pending:
                ray.cancel(reference, force=True)
        return {job.key: results[job.key] for job in jobs}

    def close(self) -> None:
        self.ray.shutdown()

    def __enter__(self) -> RayCluster:
        return self

    def __exit__(self, *exception) -> None:
        self.close()
