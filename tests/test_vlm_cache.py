"""Answer cache, Retry-After parsing, back-off bounds and prompt versioning."""

from __future__ import annotations

import email.utils
import random
import time

from vlm_vpr_ros.priors.cache import AnswerCache, cache_key, image_digest
from vlm_vpr_ros.priors.openai_client import ChatClient, parse_retry_after
from vlm_vpr_ros.priors.prompts import PROMPTS, build_messages, get_prompt


def test_cache_roundtrip_and_corruption(tmp_path):
    cache = AnswerCache(tmp_path / "c")
    key = cache_key(image_digest(b"jpeg bytes"), "gpt-4o", "ltm-v1")
    assert cache.get(key) is None
    cache.put(key, '{"latitude": 1, "longitude": 2}', model="gpt-4o")
    assert cache.get(key)["raw_text"] == '{"latitude": 1, "longitude": 2}'
    assert len(cache) == 1 and not list((tmp_path / "c").rglob("*.tmp"))
    path = next((tmp_path / "c").rglob(f"{key}.json"))
    path.write_text("{ truncated")
    assert cache.get(key) is None  # a corrupt entry is a miss, not a crash
    path.write_text('{"raw_text": 5}')
    assert cache.get(key) is None


def test_cache_key_depends_on_image_model_and_prompt():
    base = cache_key(image_digest(b"a"), "m", "ltm-v1")
    assert base == cache_key(image_digest(b"a"), "m", "ltm-v1")
    assert len({base, cache_key(image_digest(b"b"), "m", "ltm-v1"),
                cache_key(image_digest(b"a"), "n", "ltm-v1"),
                cache_key(image_digest(b"a"), "m", "ltm-v2")}) == 4


def test_parse_retry_after():
    assert parse_retry_after("7") == 7.0
    assert parse_retry_after("0.5") == 0.5
    assert parse_retry_after("-3") == 0.0
    assert parse_retry_after(None) is None and parse_retry_after("soon") is None
    now = time.time()
    date = email.utils.formatdate(now + 30, usegmt=True)
    assert 28 <= parse_retry_after(date, now=now) <= 31


def test_backoff_is_exponential_with_bounded_jitter():
    client = ChatClient("http://127.0.0.1:1/v1", backoff_s=0.5, max_backoff_s=4.0,
                        rng=random.Random(0))
    for attempt, d in [(0, 0.5), (1, 1.0), (2, 2.0), (3, 4.0), (6, 4.0)]:
        waits = [client._backoff(attempt) for _ in range(200)]
        assert d / 2 <= min(waits) and max(waits) <= d
        assert max(waits) - min(waits) > d / 4  # it is jittered


def test_prompts_are_versioned_and_ltm_goes_coarse_to_fine():
    assert get_prompt("ltm").id == "ltm-v1" and set(PROMPTS) == {"ltm", "direct"}
    text = get_prompt("ltm").user.lower()
    order = [text.index(w) for w in ("continent", "country", "region", "place", "latitude")]
    assert order == sorted(order)
    msgs = build_messages(get_prompt("ltm"), "data:image/jpeg;base64,AAAA")
    assert msgs[1]["content"][1]["image_url"]["url"].endswith("AAAA")
