"""Where a method's held-out error above the floor comes from, on a processed simulated session:
``python benchmarks/floor.py STORE [--session NAME] [--methods lensch sharing] [--set KEY=VALUE ...]``.

Reads the session's stored lumitexels (run ``gonio demo`` or ``gonio process`` first), fits each
method as ``gonio process`` does (the lab's options; ``--set`` overrides Lensch's, e.g.
``--set robust_samples=True``), and prints its held-out relative RMS beside the floor (the
simulation's true model on the same held-out samples), then splits the squared error by
cause, against the simulation's truth:

- by texel: the share of the worst 1 % of texels, and for those the fitted normal's angle to the
  true one (and the mesh normal's), whether the label is the texel's true material (each cluster
  named by its majority), the footprint spread, and whether any training sample saw the
  highlight the held-out sample shows (its true reflectance within half the held-out one);
- by held-out view, and by sample geometry: grazing view or light (cos < 0.2 about the mesh
  normal) and texels whose footprint mixes normals;
- an oracle: the truth's own materials rendered about the method's fitted normals (a method
  that beats it hedges its normals' errors with its lobes).
"""
from __future__ import annotations

import argparse
import ast
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the package, not benchmarks/capture.py

from capture.lab_resolver import resolve_lab  # noqa: E402
from capture.pipeline.cluster import ClusterOptions, Executor  # noqa: E402
from capture.pipeline.lumitexel_arrays import block_texels_for, default_memory_limit, stream_lumitexels  # noqa: E402
from capture.pipeline.methods import fit_method  # noqa: E402
from capture.pipeline.process import read_calibration, session_images, view_plan, sample_sphere_of  # noqa: E402
from capture.pipeline.run import _options, _truth_of  # noqa: E402
from capture.store import Store  # noqa: E402
from reconstruct.metrics import relative_rms  # noqa: E402


@dataclass
class Session:
    """A processed session's gathered lumitexels and the truth's reflectance of their samples."""

    train: object
    held: object
    truth: object
    true_train: np.ndarray
    true_held: np.ndarray
    options: dict


def load(root: str, name: str | None) -> Session:
    store = Store(root, durable=False)
    name = name or store.sessions()[0].name
    lab = resolve_lab(store, name)
    cal = read_calibration(store, name, gray_card=lab.gray_card, probe_reflectance=lab.probe_reflectance)
    images = session_images(store, name)
    plan = view_plan(images, name, cal, mesh=lab.require_mesh(), sample_sphere=sample_sphere_of(lab.targets))
    limit = default_memory_limit()
    with Executor(ClusterOptions(), store_root=root) as ex:
        arrays = stream_lumitexels(images, name, cal, plan, lab.require_mesh(), ex,
                                   block_texels=block_texels_for(limit, n_views=len(plan.poses),
                                                                 pixels=cal.camera.width * cal.camera.height))
    train, held = arrays.gather()
    return Session(train, held, lab.truth, _truth_of(lab.truth, train), _truth_of(lab.truth, held),
                   {m: _options(m, lab.method_options, limit, arrays) for m in ("lensch", "sharing")})


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))


def decompose(s: Session, name: str, fit) -> None:
    held, train = s.held, s.train
    pred = fit.predict(held)
    meas = held.reflectance
    floor = relative_rms(s.true_held, meas)
    score = relative_rms(pred, meas)
    print(f"\n== {name}: held-out {score:.3f}, floor {floor:.3f}, ratio {score / floor:.2f}x; "
          f"truth-vs-model {relative_rms(pred, s.true_held):.3f}")
    norm = np.sum(meas ** 2)
    e = np.sum((pred - meas) ** 2, axis=1)
    ef = np.sum((s.true_held - meas) ** 2, axis=1)
    T = train.n_texels
    per = np.bincount(held.texel, e, T)
    per_f = np.bincount(held.texel, ef, T)
    order = np.argsort(per)[::-1]
    true_n = s.truth.normals(train.position)
    true_n = train.normal if true_n is None else true_n
    ids, _ = s.truth.materials(train.position)
    fit_n = fit.normals if fit.normals is not None else train.normal
    n_err, mesh_err = _angle(fit_n, true_n), _angle(train.normal, true_n)
    labels = fit.arrays.get("labels")
    right = np.ones(T, bool)
    if labels is not None:
        named = {k: np.bincount(ids[labels == k]).argmax() for k in np.unique(labels)}
        right = np.array([named[k] for k in labels]) == ids
    # a training sample "saw" the highlight a held-out sample shows: its true value within half
    tmax = np.zeros(T)
    np.maximum.at(tmax, train.texel, s.true_train.sum(axis=1))
    unseen = s.true_held.sum(axis=1) > 2 * tmax[held.texel]
    spread = train.footprint_spread_deg if train.footprint_spread_deg is not None else np.full(T, np.nan)

    def share(mask):   # of the squared error above ... and the rel. RMS without those samples
        return f"{np.sum(e[mask]) / np.sum(e):6.1%} of error, {np.sum(ef[mask]) / np.sum(ef):6.1%} of floor's"
    has = np.bincount(held.texel, minlength=T) > 0
    top = order[:max(1, int(0.01 * np.count_nonzero(has)))]
    print(f"worst 1 % of texels ({len(top)}): {per[top].sum() / per.sum():.1%} of the squared error "
          f"(the floor's on them: {per_f[top].sum() / per_f.sum():.1%}); without them "
          f"{np.sqrt((per.sum() - per[top].sum()) / (norm - np.bincount(held.texel, np.sum(meas**2, 1), T)[top].sum())):.3f}")
    for what, v in (("fitted normal vs true (deg)", n_err), ("mesh normal vs true (deg)", mesh_err),
                    ("footprint spread (deg)", spread)):
        print(f"  {what:<30} worst-1%: median {np.nanmedian(v[top]):6.2f}  p90 {np.nanpercentile(v[top], 90):6.2f}"
              f"   all texels: median {np.nanmedian(v[has]):6.2f}  p90 {np.nanpercentile(v[has], 90):6.2f}")
    print(f"  label right: worst-1% {right[top].mean():.1%}, all {right[has].mean():.1%}")
    print(f"samples whose highlight no training sample of the texel saw: {unseen.mean():.2%} of samples, {share(unseen)}")
    cos_o, cos_i = held.wo[:, 2], held.wi[:, 2]
    for what, mask in (("grazing view (cos < 0.2)", cos_o < 0.2), ("grazing light (cos < 0.2)", cos_i < 0.2),
                       ("fitted normal > 10 deg off", (n_err > 10)[held.texel]),
                       ("fitted normal off > 2x mesh's and > 5 deg", ((n_err > 2 * mesh_err) & (n_err > 5))[held.texel]),
                       ("label wrong", ~right[held.texel]),
                       ("footprint spread > 6 deg", (np.nan_to_num(spread) > 6)[held.texel])):
        print(f"  {what:<42} {mask.mean():6.2%} of samples: {share(mask)}")
    # oracle: the truth's own materials (true labels) about the method's fitted normals. Worse
    # than the method means its lobes hedge its normals' errors, so a truer lobe alone cannot help
    if fit.normals is not None:
        oracle = _truth_of(_TruthAbout(s.truth, np.asarray(fit.normals, float)), held)
        eo = np.sum((oracle - meas) ** 2, axis=1)
        off = (n_err > 2)[held.texel]
        print(f"the true materials about the fitted normals: held-out {relative_rms(oracle, meas):.3f} "
              f"({relative_rms(oracle, meas) / floor:.2f}x the floor); on texels whose fitted normal is > 2 deg "
              f"off ({off.mean():.1%} of samples): {np.sum(eo[off]) / np.sum(eo):.1%} of its squared error")
    for v in np.unique(held.view):
        m = held.view == v
        print(f"  held-out view {v}: {m.sum()} samples, method {relative_rms(pred[m], meas[m]):.3f}, "
              f"floor {relative_rms(s.true_held[m], meas[m]):.3f}")
    # what the worst texels look like: training maximum, held-out true and predicted maximum
    for t in order[:5]:
        hm = held.texel == t
        tm = train.texel == t
        print(f"  texel {t}: {tm.sum()} training samples (max measured {train.reflectance[tm].sum(1).max():.3f}, "
              f"true {s.true_train[tm].sum(1).max():.3f}); held-out measured {meas[hm].sum(1).max():.3f} "
              f"true {s.true_held[hm].sum(1).max():.3f} predicted {pred[hm].sum(1).max():.3f}; normal "
              f"{n_err[t]:.1f} deg off (mesh {mesh_err[t]:.1f}), label {'right' if right[t] else 'wrong'}, "
              f"spread {spread[t]:.1f}")


@dataclass(frozen=True)
class _TruthAbout:
    """The simulation's truth with its normals replaced by ``given`` (T, 3, object frame), for
    :func:`capture.pipeline.run._truth_of`: the true materials seen about other normals."""

    truth: object
    given: np.ndarray

    def materials(self, points):
        return self.truth.materials(points)

    def normals(self, points):
        return self.given


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("store")
    parser.add_argument("--session")
    parser.add_argument("--methods", nargs="+", default=["lensch"])
    parser.add_argument("--rng", type=int, default=0)
    parser.add_argument("--set", nargs="*", default=[], help="Lensch options, KEY=VALUE")
    args = parser.parse_args()
    s = load(args.store, args.session)
    print(f"{s.train.n_texels} texels, {s.train.n_samples} training / {s.held.n_samples} held-out samples")
    extra = {k: ast.literal_eval(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    for m in args.methods:
        opts = {**s.options.get(m, {}), **(extra if m == "lensch" else {})}
        fit = fit_method(m, s.train, None, rng=args.rng, **opts)
        decompose(s, m, fit)


if __name__ == "__main__":
    main()
