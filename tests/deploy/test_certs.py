"""The certificates of a secure deployment: one CA signs every identity, SuperNode keys are
the OpenSSH NIST-EC keys Flower reads, each Zenoh certificate names its role."""

import ipaddress

from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.serialization import load_ssh_private_key, load_ssh_public_key

from dronefl.deploy.certs import make_certificates
from dronefl.deploy.link import common_name


def test_every_certificate_is_signed_by_the_ca_and_names_the_hosts(tmp_path):
    certs = make_certificates(tmp_path, [1, 2], hosts=("127.0.0.1", "cloud.local"))
    ca = x509.load_pem_x509_certificate(certs.ca.read_bytes())
    paths = [certs.superlink[0]] + [
        certs.zenoh(role).certificate for role in ("world", "cloud", "launcher", "drone-2")
    ]
    for path in paths:
        leaf = x509.load_pem_x509_certificate(path.read_bytes())
        leaf.verify_directly_issued_by(ca)  # raises if not signed by the CA
        names = leaf.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert ipaddress.ip_address("127.0.0.1") in names.get_values_for_type(x509.IPAddress)
        assert "cloud.local" in names.get_values_for_type(x509.DNSName)
    assert (tmp_path / "ca.key").stat().st_mode & 0o077 == 0  # private keys: owner only


def test_each_zenoh_certificate_names_its_role(tmp_path):
    # The other processes' access control knows each process by its certificate's common name.
    certs = make_certificates(tmp_path, [1, 2])
    for role in ("world", "cloud", "launcher", "drone-1", "drone-2"):
        assert common_name(certs.zenoh(role).certificate) == role


def test_supernode_keys_are_openssh_p384_pairs(tmp_path):
    certs = make_certificates(tmp_path, [3])
    private = load_ssh_private_key(certs.supernode_key(3).read_bytes(), password=None)
    public = load_ssh_public_key(certs.supernode_public_key(3).read_bytes())
    assert isinstance(private, ec.EllipticCurvePrivateKey)
    assert private.curve.name == "secp384r1"
    assert private.public_key().public_numbers() == public.public_numbers()
