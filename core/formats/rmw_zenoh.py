"""How rmw_zenoh names ROS 2 topics on Zenoh: data keys, graph liveliness tokens, attachments.

ROS 2 nodes on `rmw_zenoh_cpp` find each other through Zenoh liveliness tokens and exchange
CDR messages on plain Zenoh keys. These pure functions write those strings and bytes, so that
topseg can appear as a ROS 2 node without a ROS install (`services/live/bridge_ros2.py`).

Sources (ros2/rmw_zenoh; docs/research/ros2-interop-sources.md quotes them):
- data key `<domain_id>/<topic without its outer slashes>/<DDS type name>/<RIHS01 hash>`:
  `docs/design.md` @ 99a6a2bd10b949052f4f12c5854825dc005e95a5, built by `TopicInfo` in
  `rmw_zenoh_cpp/src/detail/liveliness_utils.cpp` @ 3411fdec149fe0c932f24d4d79ef908eb81d7482;
- liveliness tokens `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/
  <namespace>/<node name>[/<topic>/<type>/<hash>/<qos>]`, names mangled (`/` -> `%`), the QoS
  written by `qos_to_keyexpr` (only values that differ from rmw_zenoh's defaults, `qos.cpp`
  @ 7efeee2b9009b816a4bd4a3148af3cca40f753d5), the entity GID = XXH3-128 of the token:
  `liveliness_utils.cpp` @ 3411fdec;
- the attachment of every sample: sequence number, source timestamp and publisher GID, in
  Zenoh's own serialisation: `attachment_helpers.cpp` @ 534747dca92adf15e1b1b975123037ca278db5ba
  (rmw_zenoh 0.2.4 and later; Jazzy 0.2.0-0.2.3 used a labelled format this does not write).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from zenoh.ext import Int64, z_serialize

from topseg.core.errors import TopsegError
from topseg.core.formats.ros2_messages import dds_type_name, type_hash

ADMIN_SPACE = "@ros2_lv"
NODE_KIND = "NN"
PUBLISHER_KIND = "MP"
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE

# rmw/types.h enum values (Jazzy)
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2

#: a ROS 2 topic name token (rcl's topic name rules: no empty token, none starting with a digit)
_ROS_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class Ros2NameError(TopsegError):
    """A name that is not a valid absolute ROS 2 topic name."""


@dataclass(frozen=True)
class Qos:
    """The QoS policies a topseg publisher offers; deadline, lifespan and liveliness stay at
    rmw_zenoh's defaults (infinite, automatic)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10

    def keyexpr(self) -> str:
        """rmw_zenoh's compact form: `rel:dur:hist,depth:deadline:lifespan:liveliness`, each
        number written only where it differs from rmw_zenoh's default."""
        d = _RMW_ZENOH_DEFAULT

        def part(value: int, default: int) -> str:
            return "" if value == default else str(value)

        return (
            f"{part(self.reliability, d.reliability)}:{part(self.durability, d.durability)}:"
            f"{part(self.history, d.history)},{part(self.depth, d.depth)}:,:,:,,"
        )


#: rmw_zenoh's defaults (qos.cpp): reliable, volatile, keep last 42
_RMW_ZENOH_DEFAULT = Qos(RELIABLE, VOLATILE, KEEP_LAST, 42)
#: what `rclcpp::QoS(10)` offers: reliable, so best-effort and reliable readers both match
DEFAULT_QOS = Qos()
#: tf2_ros' StaticBroadcasterQoS: the last message kept for late joiners
STATIC_TF_QOS = Qos(durability=TRANSIENT_LOCAL, depth=1)


@dataclass(frozen=True)
class Node:
    """A ROS 2 node as rmw_zenoh announces it: domain, Zenoh session id, node id, names."""

    domain: int
    zid: str
    node_id: int
    name: str
    namespace: str = "/"
    enclave: str = "/"

    def token(self) -> str:
        """The node's liveliness token (its id twice: node and entity)."""
        return "/".join(self._head(self.node_id, NODE_KIND))

    def publisher_token(self, entity_id: int, topic: str, typename: str, qos: Qos) -> str:
        """The liveliness token of one of the node's publishers."""
        return "/".join(
            (
                *self._head(entity_id, PUBLISHER_KIND),
                mangle(check_topic_name(topic)),
                mangle(dds_type_name(typename)),
                mangle(type_hash(typename)),
                qos.keyexpr(),
            )
        )

    def _head(self, entity_id: int, kind: str) -> tuple[str, ...]:
        return (
            ADMIN_SPACE,
            str(self.domain),
            self.zid,
            str(self.node_id),
            str(entity_id),
            kind,
            mangle(self.enclave),
            mangle(self.namespace),
            mangle(self.name),
        )


def mangle(name: str) -> str:
    """A name as one key chunk: each `/` becomes `%`."""
    return name.replace("/", "%")


def check_topic_name(topic: str) -> str:
    """`topic` if it is an absolute ROS 2 topic name; Ros2NameError saying why not."""
    tokens = topic.split("/")
    if tokens[0] != "" or len(tokens) < 2 or not all(_ROS_TOKEN.fullmatch(t) for t in tokens[1:]):
        raise Ros2NameError(
            f"{topic!r} is not a ROS 2 topic name: '/'-separated tokens of letters, digits "
            "and '_', none starting with a digit"
        )
    return topic


def topic_key(domain: int, topic: str, typename: str) -> str:
    """The Zenoh key a topic's messages go on: `<domain>/<topic>/<DDS type>/<RIHS01 hash>`."""
    name = check_topic_name(topic).strip("/")
    return f"{domain}/{name}/{dds_type_name(typename)}/{type_hash(typename)}"


def entity_gid(token: str) -> bytes:
    """An entity's 16-byte GID: XXH3-128 of its liveliness token, low then high 64 bits,
    little-endian (what every rmw_zenoh process derives from the token)."""
    import xxhash

    digest = xxhash.xxh3_128_intdigest(token.encode())
    return (digest & (2**64 - 1)).to_bytes(8, "little") + (digest >> 64).to_bytes(8, "little")


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """A sample's attachment: int64 sequence number, int64 source time (ns since the epoch),
    then the GID as a length-prefixed byte sequence, in Zenoh's serialisation (33 bytes)."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, got {len(gid)}")
    return z_serialize((Int64(sequence_number), Int64(source_timestamp_ns), bytes(gid))).to_bytes()
