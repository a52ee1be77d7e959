"""A result and a step in words: the one place a result becomes text (`skyview.present.drawables`'s text half).

`result_lines` (status, why not, attitude, sigma, verification, time), `why_not` (why a solve failed, in
one sentence a student understands, and what to try), `step_summary`, `format_number`. The viewer's
panel and the recording's result document both use them.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from skyview.present.drawables import StepView

def format_number(v: float) -> str:
    """Compact, readable figure: integers as such, small probabilities in scientific notation."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if float(v).is_integer() and abs(v) < 1e9:
        return f"{int(v):d}"
    a = abs(v)
    if a != 0 and (a < 1e-3 or a >= 1e6):
        return f"{v:.3g}"
    if a < 1:
        return f"{v:.4f}"
    if a < 100:
        return f"{v:.3f}"
    return f"{v:.1f}"


def step_summary(v: StepView) -> str:
    """One line: what the step shows, with the surviving count (never the sample size alone)."""
    parts = [f"observed: {', '.join(map(str, v.observed.tolist())) or '-'}"]
    if v.surviving is not None:
        parts.append(f"{v.surviving} surviving hypotheses ({v.drawn} drawn)")
    elif v.drawn:
        parts.append(f"{v.drawn} candidate groups drawn")
    return " · ".join(parts)


def result_lines(result) -> list[tuple[str, str]]:
    """The result of a solve as (label, value) rows: the one place a result becomes text.

    result: a `pipeline.SolveResult`. Status and the reason when not solved (with `why_not`), the
    attitude and its 1-sigma, the matches and the verification, the time per stage."""
    from skyview.core.attitude import radec_roll_from_R

    rows = [("status", f"{'solved' if result.solved else 'not solved'} by {result.method} ({result.variant})")]
    if not result.solved:  # one line (a table cell): the bullets of a blind solve's story run on
        rows.append(("why", why_not(result).replace("\n- ", " • ").replace("\n", " ")))
    c = result.centroids
    rows.append(("centroids / matched", f"{len(c)} / {len(result.matches)}"
                 + (f" (of {c.n_detected} detected, the brightest measured)" if c.n_unmeasured else "")))
    if result.R is not None:
        ra, dec, roll = (math.degrees(x) for x in radec_roll_from_R(result.R))
        rows += [("RA / Dec / roll", f"{ra:.5f}° / {dec:+.5f}° / {roll:+.4f}°")]
        if result.sigma_boresight_arcsec is not None:
            rows.append(("1σ boresight / roll", f"{result.sigma_boresight_arcsec:.2f}\" / "
                                               f"{result.sigma_roll_arcsec:.1f}\""))
    ident = result.identification
    ver = ident.verification if ident is not None else {}
    if ver.get("n_tested"):
        rows.append(("verification", f"{int(ver.get('n_agree', 0))} of {int(ver['n_tested'])} stars agree, "
                                     f"P(false) {format_number(float(ver.get('p_false', float('nan'))))}"))
    if result.time_ms:
        rows.append(("time", ", ".join(f"{k} {v:.1f} ms" for k, v in result.time_ms.items())))
    return rows


SEARCH_WHAT = {  # a blind search's kind (`SolveResult.searches`), in words
    "pinhole": "patterns of four stars in the guide catalog (Hipparcos-2), a pinhole lens",
    "narrow": "a narrow field: patterns in the deep catalog (Hipparcos-2 and Gaia DR3 to G 10)",
    "fisheye": "a fisheye lens (equidistant and equisolid, their distortion fitted)",
}


def blind_searches(result) -> list[dict]:
    """The searches a blind solve ran (`SolveResult.searches`), one per kind and set of stars (a fisheye's two
    lenses together), in the order they ran: {"kind", "what", "fov" (e.g. "2.5-81°"), "stars",
    "hypotheses", "outcome"} in words."""
    out: list[dict] = []
    for srch in getattr(result, "searches", None) or []:
        same = next((o for o in out if o["kind"] == srch["kind"] and o["stars"] == srch["stars"]), None)
        if same is None:
            same = {"kind": srch["kind"], "what": SEARCH_WHAT.get(srch["kind"], srch["kind"]), "stars": srch["stars"],
                    "lo": srch["fov_deg"][0], "hi": srch["fov_deg"][1], "hypotheses": 0}
            out.append(same)
        same["lo"], same["hi"] = min(same["lo"], srch["fov_deg"][0]), max(same["hi"], srch["fov_deg"][1])
        same["hypotheses"] += srch["hypotheses"]
    for o in out:
        o["fov"] = f"{_deg1(o.pop('lo'))}-{_deg1(o.pop('hi'))}°"
        o["outcome"] = ("every candidate attitude was checked against the other stars: too few of them fell on "
                        "catalog stars to rule out chance") if o["hypotheses"] else \
            "no catalog pattern matched the brightest stars"
    return out


def _deg1(x: float) -> str:
    return f"{x:.1f}".rstrip("0").rstrip(".")


def blind_story(result) -> str:
    """Why the default pipeline (blind) did not solve a user's image, in words: what it found, what it
    tried and what to try next (Markdown bullets)."""
    n = len(result.centroids)
    if n < 4:
        return (f"Only {n} star{'s' if n != 1 else ''} found in the image: a pattern needs four, and a confirmation "
                f"several more. Try a longer exposure, or a photograph with more sky in it.")
    lines = [f"skyview found {n} stars, formed patterns of four from the brightest and looked them up:"]
    for srch in blind_searches(result):
        hyp = f" ({srch['hypotheses']:,} candidate attitudes)" if srch["hypotheses"] else ""
        more = f", with the {srch['stars']} stars a deeper look found" if srch["stars"] != n else ""
        lines.append(f"- {srch['what']} over {srch['fov']}{more}{hyp}: {srch['outcome']}.")
    lines.append("What to try: if you know the camera's field of view, give it (the FOV hint, or `--fov-deg`); if "
                 "the brightest spots are not stars (street lamps, a lit roof, the Moon, a planet, hot pixels), crop "
                 "them out; fields narrower than 0.7° or wider than 81° through an ordinary (not fisheye) lens are "
                 "outside what skyview searches.")
    return "\n".join(lines)


def blind_summary(result) -> str:
    """A failed blind solve in one short line (the status line; `blind_story` tells the rest)."""
    n = len(result.centroids)
    if n < 4:
        return f"only {n} star{'s' if n != 1 else ''} found: too few for a pattern"
    searches = blind_searches(result)
    hyp = sum(s_["hypotheses"] for s_ in searches)
    named = {"pinhole": "pinhole", "narrow": "narrow fields", "fisheye": "fisheye"}
    kinds = ", ".join(dict.fromkeys(f"{named.get(s_['kind'], s_['kind'])} {s_['fov']}" for s_ in searches))
    return (f"no candidate attitude was confirmed by the other stars ({n} stars; searched {kinds}"
            + (f"; {hyp:,} hypotheses" if hyp else "") + "): the Result tab says what to try")


def why_not(result) -> str:
    """Why a solve failed, in one sentence a student understands, and what to try."""
    if result.method == "blind":
        return blind_story(result)
    ident = result.identification
    n = len(result.centroids)
    reason = (result.reason or (ident.reason if ident is not None else "")).strip()
    paper = _paper_conditions(result)
    if ident is None or n < 3:
        return (f"Only {n} star{'s' if n != 1 else ''} found in the image: too few to form a pattern. "
                f"Try a wider field of view, a deeper magnitude limit or a longer exposure.")
    ver = ident.verification or {}
    low = reason.lower()
    if "no catalog" in low or "no hypothesis survives" in low or "no pattern matches" in low or "none within" in low:
        text = ("No catalog pattern matches the measured one within the noise bound: a false star or a star "
                "missing from the catalog may be in it. Try a larger noise bound (--sigma), the improved variant "
                "or another method.")
    elif ver.get("n_tested") and not ident.identified:
        text = (f"The best guess was checked against the whole image and only {int(ver.get('n_agree', 0))} of "
                f"{int(ver['n_tested'])} stars landed on a catalog star, which chance could explain. Try the "
                f"improved variant or the default pipeline.")
    elif "hypotheses left" in low or "ambiguous" in low or "several" in low:
        text = ("Several catalog patterns fit the measured one equally well and no further star told them apart. "
                "Try a deeper magnitude limit (more stars) or the improved variant.")
    else:
        text = (reason[0].upper() + reason[1:] + ".") if reason else "The method found no verified answer."
        text += " Try the improved variant or the default pipeline."
    return (paper + " " + text) if paper else text


def _paper_conditions(result) -> str:
    """A sentence when the scene is outside the conditions of the method's paper (its scenario)."""
    from skyview.simulate.scenarios import SCENARIOS

    name = paper_scenario(result.method)
    sc = SCENARIOS.get(name) if name else None
    if sc is None or result.variant != "paper":
        return ""
    fov = result.camera.fov_deg
    cam = sc.camera()
    far = abs(fov - cam.fov_deg) > 0.25 * cam.fov_deg
    mag = result.mag_limit
    shallow = mag is not None and mag < sc.mag_limit - 0.5
    if not (far or shallow):
        return ""
    here = f"{fov:.0f}° field" + (f", stars to Hp {mag:.1f}" if mag is not None else "")
    return (f"This scene ({here}) is outside the conditions of {result.method}'s paper "
            f"({cam.fov_deg:.0f}° field, stars to Hp {sc.mag_limit:g}).")


def paper_scenario(method: str) -> str | None:
    """The scenario of a method's paper (its `paper_scenario`), None for a method without one (blind)."""
    from skyview.identify import METHODS

    cls = METHODS.get(method)
    return getattr(cls, "paper_scenario", None) if cls is not None else None
