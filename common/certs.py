"""`d3rqn-certs` (or `python -m common.certs`): a run's CA and one certificate per role or host.

Uses the system ``openssl`` binary (no Python dependency). Every key is an ECDSA P-256 key
in PKCS#8 PEM, as Zenoh's TLS (rustls) reads it; every certificate is valid as a server
(listening) and as a client (connecting) certificate, with the common name (CN) that the
router's access rules match and, as subject alternative names, localhost, 127.0.0.1 and
the addresses given with --address (the hub's: a connecting process checks them).

    d3rqn-certs certs --address hub.example --address 10.0.0.1    # CA + replay, learner, actor, recorder
    d3rqn-certs certs --name actor-b7 --cn actor                   # one more actor host, same CA

Files: ``ca.pem`` (give it to every host), ``ca-key.pem`` (keep it on the machine that
issues certificates, nowhere else), and ``<name>.pem`` + ``<name>-key.pem`` per certificate
(copy each pair to its host only). Keys are written readable by their owner only. An
existing CA is reused; an existing certificate is never overwritten.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROLE_NAMES = ("replay", "learner", "actor", "recorder")  # the CNs TransportConfig's acl_* lists expect
DEFAULT_DAYS = 365


class CertError(RuntimeError):
    pass


def _openssl(*args: str) -> None:
    binary = shutil.which("openssl")
    if binary is None:
        raise CertError("the openssl command is not installed (apt-get install openssl)")
    result = subprocess.run([binary, *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise CertError(f"openssl {args[0]} failed: {result.stderr.strip()}")


def _private(path: Path) -> None:
    os.chmod(path, 0o600)


def _subject(common_name: str) -> str:
    if not common_name or any(char in common_name for char in "/=+,\\\n"):
        raise CertError(f"common name {common_name!r} must be non-empty, without '/', '=', '+', ',' or '\\'")
    return f"/CN={common_name}"


def _alt_names(addresses: list[str]) -> str:
    names = []
    for address in ["localhost", "127.0.0.1", *addresses]:
        try:
            entry = f"IP:{ipaddress.ip_address(address)}"
        except ValueError:
            entry = f"DNS:{address}"
        if entry not in names:
            names.append(entry)
    return ",".join(names)


def make_ca(directory: Path, days: int = DEFAULT_DAYS, name: str = "d3rqn run CA") -> tuple[Path, Path]:
    """directory/ca.pem and ca-key.pem; an existing CA is kept."""
    certificate, key = directory / "ca.pem", directory / "ca-key.pem"
    if certificate.exists() and key.exists():
        return certificate, key
    if certificate.exists() or key.exists():
        raise CertError(f"{directory} holds only half a CA (ca.pem or ca-key.pem): remove it or restore the other")
    directory.mkdir(parents=True, exist_ok=True)
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
             "-keyout", str(key), "-out", str(certificate), "-days", str(days), "-subj", _subject(name),
             "-addext", "basicConstraints=critical,CA:TRUE,pathlen:0",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign")
    _private(key)
    return certificate, key


def issue(directory: Path, name: str, common_name: str | None = None, addresses: list[str] = (),
          days: int = DEFAULT_DAYS) -> tuple[Path, Path]:
    """directory/<name>.pem and <name>-key.pem, signed by directory's CA, CN common_name (default name)."""
    if not name or "/" in name or name.startswith("."):
        raise CertError(f"certificate name {name!r} must be a plain file name")
    if name in ("ca",):
        raise CertError("'ca' is the CA's own file name")
    ca_certificate, ca_key = directory / "ca.pem", directory / "ca-key.pem"
    if not (ca_certificate.exists() and ca_key.exists()):
        raise CertError(f"no CA in {directory} (ca.pem and ca-key.pem): make one first")
    certificate, key = directory / f"{name}.pem", directory / f"{name}-key.pem"
    for path in (certificate, key):
        if path.exists():
            raise CertError(f"{path} exists: remove it to issue {name!r} again")
    extensions = "\n".join([
        "basicConstraints=critical,CA:FALSE",
        "keyUsage=critical,digitalSignature",
        "extendedKeyUsage=serverAuth,clientAuth",
        f"subjectAltName={_alt_names(list(addresses))}",
        ""])
    with tempfile.TemporaryDirectory() as scratch:
        request, extfile = Path(scratch) / "request.csr", Path(scratch) / "extensions.cnf"
        extfile.write_text(extensions)
        _openssl("req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                 "-keyout", str(key), "-out", str(request), "-subj", _subject(common_name or name))
        _private(key)
        _openssl("x509", "-req", "-in", str(request), "-CA", str(ca_certificate), "-CAkey", str(ca_key),
                 "-set_serial", str(int.from_bytes(os.urandom(16), "big") >> 1), "-days", str(days),
                 "-extfile", str(extfile), "-out", str(certificate))
    return certificate, key


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="d3rqn-certs",
        description="Makes a run's CA (once) and certificates signed by it, for TLS, mutual TLS and the "
                    "router's access rules (docs/security.md). Without --name: the four role "
                    f"certificates {', '.join(ROLE_NAMES)} (CN = the name).")
    parser.add_argument("directory", type=Path, help="where the CA and certificates go (created if missing)")
    parser.add_argument("--address", action="append", default=[], metavar="HOST",
                        help="a name or IP address the hub is reached at, added to every certificate made "
                             "now (repeat for several; localhost and 127.0.0.1 are always in)")
    parser.add_argument("--name", action="append", default=[],
                        help="make this certificate instead of the four roles' (repeatable); files <name>.pem, <name>-key.pem")
    parser.add_argument("--cn", help="the common name of the --name certificates (default: each name); "
                                     "the router's acl_* lists match it, e.g. --cn actor for one more actor host")
    parser.add_argument("--days", type=int, default=DEFAULT_DAYS, help=f"validity (default {DEFAULT_DAYS})")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    names = args.name or list(ROLE_NAMES)
    try:
        if args.days <= 0:
            raise CertError("--days must be > 0")
        for name in names:
            if (args.directory / f"{name}.pem").exists():
                raise CertError(f"{args.directory / f'{name}.pem'} exists: remove it to issue {name!r} again")
        ca, _ = make_ca(args.directory, args.days)
        print(f"CA           {ca}")
        for name in names:
            certificate, key = issue(args.directory, name, args.cn or name, args.address, args.days)
            print(f"{name:<12} {certificate}  {key}  (CN {args.cn or name})")
    except CertError as error:
        print(f"d3rqn-certs: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
