"""The frame ids the sensors stamp their messages with (``header.frame_id``)."""

from __future__ import annotations

import logging
from pathlib import Path

from licalib_cli.errors import LicalibError
from licalib_cli.io.bag import open_bag

__all__ = ["frame_ids"]

logger = logging.getLogger(__name__)


def frame_ids(bag: Path, topics: tuple[str, ...]) -> dict[str, str]:
    """``header.frame_id`` of the first readable message of each topic.

    Args:
        bag: the bag (any supported form).
        topics: the topics to look at.

    Returns:
        Topic -> frame id; a topic without a readable message (or a bag that cannot be read
        again) is left out, so that a missing name never stops a calibration.
    """
    found: dict[str, str] = {}
    try:
        with open_bag(Path(bag)) as handle:
            for message in handle.messages(list(topics)):
                if message.topic in found:
                    continue
                decoded = handle.decode(message)
                header = getattr(decoded, "header", None)
                frame = getattr(header, "frame_id", None)
                if isinstance(frame, str):
                    found[message.topic] = frame
                if len(found) == len(set(topics)):
                    break
    except LicalibError as err:
        logger.debug("frame ids of %s not read: %s", bag, err)
    return found
