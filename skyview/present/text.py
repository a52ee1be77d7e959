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


def blind_searches(reason: str) -> list[dict]:
    """The searches a failed blind solve ran, read from its reason (`skyview.solver.pipeline`: the guide
    catalog's pinhole search, then "as a narrow field in the deep catalog: ...", "as a fisheye (A-B deg):
    ..."): each as {"what", "fov" (the range searched, or ""), "hypotheses" (int or None), "outcome"}."""
    import re

    out = []
    for k, part in enumerate(re.split(r"; as (?:a )?", reason or "")):
        part = part.strip()
        if not part:
            continue
        if k == 0:
            what = "patterns of four stars in the guide catalog (Hipparcos-2), a pinhole lens"
        elif part.startswith("narrow field"):
            what = "a narrow field: patterns in the deep catalog (Hipparcos-2 and Gaia DR3 to G 10)"
            part = part.split(":", 1)[1].strip() if ":" in part else part
        elif part.startswith("fisheye"):
            what = "a fisheye lens (equidistant and equisolid, their distortion fitted)"
        else:
            what = part.split(":", 1)[0]
        fov = re.search(r"(?:searched FOVs?|fisheye \()\s*([0-9.]+)-([0-9.]+) deg", part)
        hyp = re.search(r"after (\d+) hypotheses", part)
        if "not confirmed" in part or "chance" in part:
            outcome = "every candidate attitude was checked against the other stars: too few of them fell on catalog " \
                      "stars to rule out chance"
        elif "no catalog pattern" in part or "too few" in part:
            outcome = "no catalog pattern matched the brightest stars"
        else:
            outcome = part.split(";")[0]
        out.append({"what": what, "fov": f"{float(fov[1]):g}-{float(fov[2]):g}°" if fov else "",
                    "hypotheses": int(hyp[1]) if hyp else None, "outcome": outcome})
    return out


def blind_story(result) -> str:
    """Why the default pipeline (blind) did not solve a user's image, in words: what it found, what it
    tried and what to try next (Markdown bullets)."""
    n = len(result.centroids)
    if n < 4:
        return (f"Only {n} star{'s' if n != 1 else ''} found in the image: a pattern needs four, and a confirmation "
                f"several more. Try a longer exposure, or a photograph with more sky in it.")
    lines = [f"skyview found {n} stars, formed patterns of four from the brightest and looked them up:"]
    for srch in blind_searches(result.reason):
        fov = f" over {srch['fov']}" if srch["fov"] else ""
        hyp = f" ({srch['hypotheses']:,} candidate attitudes)" if srch["hypotheses"] else ""
        lines.append(f"- {srch['what']}{fov}{hyp}: {srch['outcome']}.")
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
    searches = blind_searches(result.reason)
    hyp = sum(s_["hypotheses"] or 0 for s_ in searches)
    kinds = ", ".join(f"{w} {s_['fov']}".strip() for w, s_ in zip(("pinhole", "narrow fields", "fisheye"), searches))
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
