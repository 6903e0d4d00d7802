"""Prompts sent to the VLM, versioned in one place.

The version string of a prompt is part of the answer-cache key: edit a prompt's text and you
must bump its version, so cached answers of the old prompt are never reused for the new one.

``ltm`` is least-to-most prompting: the model narrows down from the continent to the country,
then the region and nearest city, then the most specific place it can name, and only then gives
the coordinates of that place, as one JSON object. ``direct`` asks for the coordinates only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from vlm_vpr_ros.config import choose


@dataclass(frozen=True)
class Prompt:
    name: str
    version: str
    system: str
    user: str

    @property
    def id(self) -> str:
        """``name-version``, e.g. ``ltm-v1``: the cache key component."""
        return f"{self.name}-{self.version}"


_LTM_SYSTEM = (
    "You are a geolocation expert who estimates where a photograph was taken from what is "
    "visible in it: landscape, vegetation, climate, architecture, road markings, signs, "
    "scripts and languages, vehicles and which side of the road they drive on."
)

_LTM_USER = """\
Estimate where this photo was taken. Solve it as a sequence of easier sub-problems, each one \
building on the answer to the previous one:

1. Continent: which continent is it on, and which clues tell you so?
2. Country: within that continent, which country? Name the clues.
3. Region and city: within that country, which state or region, and which nearest city or town?
4. Place: within that area, the most specific place you can name (district, street, landmark).
5. Coordinates: the latitude and longitude of that place in decimal degrees.

Always commit to a best guess at every step; an approximate answer is far more useful than no \
answer, and nobody will rely on it as exact. Keep each reason short.

Reply with exactly one JSON object and nothing else (no code fences, no text around it):
{"continent": "...", "country": "...", "region": "...", "city": "...", "place": "...", \
"reasons": "one or two sentences", "latitude": <number between -90 and 90>, \
"longitude": <number between -180 and 180>}"""

_DIRECT_USER = """\
Where was this photo taken? Give your best guess even if unsure. Reply with exactly one JSON \
object and nothing else: {"latitude": <number between -90 and 90>, \
"longitude": <number between -180 and 180>}"""

PROMPTS: dict[str, Prompt] = {
    "ltm": Prompt("ltm", "v1", _LTM_SYSTEM, _LTM_USER),
    "direct": Prompt("direct", "v1", _LTM_SYSTEM, _DIRECT_USER),
}


def get_prompt(name: str) -> Prompt:
    """The prompt called ``name``; an unknown name is a ConfigError listing the choices."""
    return choose(name, PROMPTS, "prompt")


def build_messages(prompt: Prompt, image_data_url: str) -> list[dict[str, Any]]:
    """Chat-completions ``messages``: the system text, then the question and the image."""
    return [
        {"role": "system", "content": prompt.system},
        {"role": "user", "content": [
            {"type": "text", "text": prompt.user},
            {"type": "image_url", "image_url": {"url": image_data_url}},
        ]},
    ]


_TEXT_FIELDS = {
    "ltm": ("continent", "country", "region", "city", "place", "reasons"),
    "direct": (),
}


def response_format(prompt: Prompt, uncertainty: bool = False) -> dict[str, Any]:
    """The ``response_format`` of structured output for ``prompt``: a strict JSON schema with
    the prompt's reasoning fields first (the model writes them before the coordinates, as the
    prompt asks), then ``latitude`` and ``longitude`` in decimal degrees, and with
    ``uncertainty`` the model's own error radius ``uncertainty_km``."""
    props: dict[str, Any] = {k: {"type": "string"} for k in _TEXT_FIELDS.get(prompt.name, ())}
    # the strictest common subset of the providers' schema modes: every field required, no
    # numeric constraints (ranges are in the descriptions; the parser checks them)
    props["latitude"] = {"type": "number",
                         "description": "latitude of the photo in decimal degrees, -90 to 90"}
    props["longitude"] = {"type": "number", "description": "longitude of the photo in decimal "
                                                           "degrees, -180 to 180"}
    if uncertainty:
        props["uncertainty_km"] = {
            "type": "number",
            "description": "your own estimate of how far off the coordinates may be: the "
                           "radius in km holding the true position with about 68 % "
                           "probability (>= 0)"}
    name = f"geolocation_{prompt.name}{'_u' if uncertainty else ''}"
    return {"type": "json_schema", "json_schema": {
        "name": name, "strict": True,
        "schema": {"type": "object", "properties": props, "required": list(props),
                   "additionalProperties": False}}}
