#!/usr/bin/env python3
"""Research prototype (session 62), not part of the tool: how far the
photo-consistency of the map's planes across the images would move a finished
model as one similarity (7 degrees of freedom), against the truth.

For up to MAX_PATCHES of the model's tracks (seen at least twice, near a map
plane, no other surface within EDGE_M): a (2 HALF + 1)^2 pixel grid around
the track in its most frontal image is cast onto the map's plane (normal of
the nearest map point, offset averaged over a 0.1 m cylinder) and sampled in
the track's other images; the residual is the difference of the
zero-mean, unit-variance patches. Pairs below MIN_ZNCC at the start are left
out. The similarity moves every camera; Gauss-Newton with central
differences. Prints the camera-centre median against the truth before and
after each iteration.

Needs numpy, scipy and pillow. A scene folder from `scripts/bench_scenes.sh`:
  photometric_similarity.py SCENE_DIR MODEL_DIR HALF MAX_PATCHES ITERATIONS MAP_PLY EDGE_M MIN_ZNCC
e.g. corridor-0 corridor-0/default-exact/model 4 3000 4 corridor-0/lidar.ply 0.06 0.8
"""
import sys, numpy as np
from PIL import Image
from scipy.spatial import cKDTree
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation
d = sys.argv[1]; model = sys.argv[2]
def qrot(q):
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
def read_images(p):
    L = [l for l in open(p) if not l.startswith('#')]
    out = {}
    for i in range(0, len(L), 2):
        t = L[i].split()
        if not t: continue
        out[t[9]] = (int(t[0]), qrot(list(map(float, t[1:5]))), np.array(list(map(float, t[5:8]))))
    return out
cam = [l for l in open(d + '/gt/cameras.txt') if l.strip() and not l.startswith('#')][0].split()
f, cx, cy, k = map(float, cam[4:8])
gt = read_images(d + '/gt/images.txt')
mod = read_images(model + '/images.txt')
byid = {v[0]: n for n, v in mod.items()}
tracks = []
for l in open(model + '/points3D.txt'):
    if l.startswith('#'): continue
    t = l.split()
    ims = sorted(set(int(x) for x in t[8::2]))
    if len(ims) >= 2:
        tracks.append((np.array(list(map(float, t[1:4]))), ims))
MAP = sys.argv[6] if len(sys.argv) > 6 else d + '/lidar.ply'
with open(MAP, 'rb') as fh:
    hdr = b''
    while not hdr.endswith(b'end_header\n'): hdr += fh.read(1)
    n = int([l for l in hdr.split(b'\n') if l.startswith(b'element vertex')][0].split()[2])
    dt = np.dtype([('x','<f8'),('y','<f8'),('z','<f8'),('nx','<f4'),('ny','<f4'),('nz','<f4')])
    M = np.frombuffer(fh.read(n*dt.itemsize), dtype=dt)
XYZ = np.stack([M['x'], M['y'], M['z']], 1); NRM = np.stack([M['nx'], M['ny'], M['nz']], 1).astype(float)
tree = cKDTree(XYZ)
imgs = {mod[name][0]: np.asarray(Image.open(f'{d}/images/{name}').convert('L'), dtype=np.float64) for name in mod}
def project(R, t, P):
    c = P @ R.T + t
    x, y = c[:, 0] / c[:, 2], c[:, 1] / c[:, 2]
    s = 1 + k * (x * x + y * y)
    return f * x * s + cx, f * y * s + cy, c[:, 2]
def plane_at(X):
    _, j = tree.query(X)
    nrm = NRM[j]
    nb = tree.query_ball_point(X, 0.15)
    L = XYZ[nb]; N = NRM[nb]
    same = N @ nrm > 0.97
    v = L[same] - XYZ[j]
    along = v @ nrm
    lat = np.linalg.norm(v - np.outer(along, nrm), axis=1)
    sel = (lat < 0.1) & (np.abs(along) < 0.05)
    if sel.sum() < 5: return None
    return nrm, (L[same][sel] @ nrm).mean()
CEN = np.mean([-R.T @ t for (_, R, t) in mod.values()], axis=0)
def centres(x):
    w, tr, ls = x[:3], x[3:6], x[6]
    R = Rotation.from_rotvec(w).as_matrix(); s = np.exp(ls)
    errs = []
    for name, (i, Rm, tm) in mod.items():
        C2 = s * R @ (-Rm.T @ tm - CEN) + CEN + tr
        _, Rg, tg = gt[name]
        errs.append(np.linalg.norm(C2 - (-Rg.T @ tg)))
    return np.array(errs) * 1000
def truth_sim3():
    A = np.array([-Rm.T @ tm for (_, Rm, tm) in mod.values()])
    B = np.array([-gt[n][1].T @ gt[n][2] for n in mod])
    ma, mb = A.mean(0), B.mean(0); A0, B0 = A - ma, B - mb
    U, S, Vt = np.linalg.svd(B0.T @ A0)
    D = np.eye(3); D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    Rt = U @ D @ Vt; st = (S * np.diag(D)).sum() / (A0 ** 2).sum()
    tt = mb - st * Rt @ ma + st * Rt @ CEN - CEN
    return np.concatenate([Rotation.from_matrix(Rt).as_rotvec(), tt, [np.log(st)]])

HALF = int(sys.argv[3]) if len(sys.argv) > 3 else 4
MAXT = int(sys.argv[4]) if len(sys.argv) > 4 else 4000
g = np.arange(-HALF, HALF + 1)
EDGE_M = float(sys.argv[7]) if len(sys.argv) > 7 else 0.06
MINZ = float(sys.argv[8]) if len(sys.argv) > 8 else 0.8

def unproject(u, v):
    x = (u - cx) / f; y = (v - cy) / f
    xu, yu = x.copy(), y.copy()
    for _ in range(20):
        r2 = xu * xu + yu * yu
        xu = x / (1 + k * r2); yu = y / (1 + k * r2)
    return np.stack([xu, yu, np.ones_like(xu)], -1)

rng = np.random.default_rng(0)
order = rng.permutation(len(tracks))
refs = []  # per patch: ref image, cam-frame dirs (NS,3), ref values (NS,), plane n, d, others
for idx in order:
    X, ims = tracks[idx]
    pl = plane_at(X)
    if pl is None: continue
    nrm, off = pl
    nb = tree.query_ball_point(X, EDGE_M)
    if (np.abs(NRM[nb] @ nrm) < 0.9).any(): continue
    dist = nrm @ X - off
    if abs(dist) > 0.02: continue
    Xs = X - nrm * dist
    best = None
    for i in ims:
        _, R, t = mod[byid[i]]
        C = -R.T @ t; vv = C - Xs
        c = abs(nrm @ vv) / np.linalg.norm(vv)
        if best is None or c > best[0]: best = (c, i)
    ref = best[1]
    _, R, t = mod[byid[ref]]
    u, v, z = project(R, t, Xs[None])
    u0, v0 = np.floor(u[0]) + 0.5, np.floor(v[0]) + 0.5
    U = (u0 + g[None, :]).repeat(len(g), 0).ravel(); V = (v0 + g[:, None]).repeat(len(g), 1).ravel()
    if U.min() < 3 or V.min() < 3 or U.max() > 636 or V.max() > 476: continue
    a = imgs[ref][(V - 0.5).astype(int), (U - 0.5).astype(int)]
    a = a - a.mean(); sd = a.std()
    if sd < 3: continue
    others = [i for i in ims if i != ref]
    refs.append((ref, unproject(U, V), a / sd, nrm, off, others))
    if len(refs) >= MAXT: break
print('patches', len(refs))
NS = len(g) ** 2
pair_p = np.array([p for p, r in enumerate(refs) for _ in r[5]])
pair_i = np.array([i for r in refs for i in r[5]])
pair_ref = np.array([refs[p][0] for p in pair_p])
DIRS = np.array([r[1] for r in refs]); REFV = np.array([r[2] for r in refs])
NRMS = np.array([r[3] for r in refs]); OFFS = np.array([r[4] for r in refs])

def moved_poses(x):
    w, tr, ls = x[:3], x[3:6], x[6]
    Rs = Rotation.from_rotvec(w).as_matrix(); s = np.exp(ls)
    out = {}
    for name, (i, R, t) in mod.items():
        C = -R.T @ t
        C2 = s * Rs @ (C - CEN) + CEN + tr
        R2 = R @ Rs.T
        out[i] = (R2, C2)
    return out

def residuals(x):
    poses = moved_poses(x)
    # plane points of every pair: ray of its reference pixel
    r = np.zeros((len(pair_p), NS))
    for ref in np.unique(pair_ref):
        R2, C2 = poses[ref]
        sel = np.where(pair_ref == ref)[0]
        P = pair_p[sel]
        dw = DIRS[P] @ R2  # (m,NS,3): R2^T d -> row vec d @ R2
        denom = np.einsum('mj,msj->ms', NRMS[P], dw)
        tt = (OFFS[P] - NRMS[P] @ C2)[:, None] / denom
        Xw = C2 + tt[..., None] * dw
        for i in np.unique(pair_i[sel]):
            s2 = np.where(pair_i[sel] == i)[0]
            Ri, Ci = poses[i]
            q = Xw[s2].reshape(-1, 3)
            u, v, z = project(Ri, -Ri @ Ci, q)
            b = map_coordinates(imgs[i], [v - 0.5, u - 0.5], order=3, mode='nearest').reshape(len(s2), NS)
            uu = u.reshape(len(s2), NS); vv = v.reshape(len(s2), NS)
            inside = (uu.min(1) > 2) & (vv.min(1) > 2) & (uu.max(1) < 637) & (vv.max(1) < 477)
            b = b - b.mean(1, keepdims=True); sd = b.std(1)
            good = inside & (sd > 2)
            rows = sel[s2]
            r[rows[good]] = b[good] / sd[good, None] - REFV[P[s2][good]]
    return r.ravel()

def wres(x):
    return (residuals(x).reshape(len(pair_p), NS) * np.sqrt(W)[:, None]).ravel()
def cost(x):
    return (wres(x) ** 2).sum()
r0 = residuals(np.zeros(7)).reshape(len(pair_p), NS)
zncc = 1 - (r0 ** 2).mean(1) / 2
W = (zncc >= MINZ).astype(float)
print('pairs', len(W), 'kept', int(W.sum()), 'median zncc %.3f' % np.median(zncc))

x0 = np.zeros(7)
xt = truth_sim3()
print('before %.3f mm cost %.1f; truth %.3f mm cost %.1f' % (np.median(centres(x0)), cost(x0), np.median(centres(xt)), cost(xt)))
for a in [-1.0, 0.5, 1.5, 2.0, 3.0]:
    print('line', a, '%.1f' % cost(a * xt))
# Gauss-Newton with central differences
steps = np.array([2e-6] * 3 + [2e-5] * 3 + [2e-6])
x = x0.copy()
for it in range(int(sys.argv[5]) if len(sys.argv) > 5 else 6):
    r0 = wres(x)
    J = np.stack([(wres(x + e) - wres(x - e)) / (2 * h) for e, h in ((np.eye(7)[j] * steps[j], steps[j]) for j in range(7))], 1)
    H = J.T @ J; gvec = J.T @ r0
    dx = -np.linalg.solve(H + 1e-9 * np.diag(np.diag(H)), gvec)
    x = x + dx
    print('it', it, 'cost %.1f -> %.1f' % ((r0 ** 2).sum(), cost(x)), 'median %.3f mm' % np.median(centres(x)), 'scale %.6f' % np.exp(x[6]))
sig = np.sqrt(np.diag(np.linalg.inv(H)) * (r0 ** 2).sum() / (len(r0) - 7))
print('x', x, 'sigma', sig)
print('truth', xt)
