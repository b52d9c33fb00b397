"""The robust observer in recursive form (lbo.models.recursive): one step at a time with its
state carried, the same numbers in a batch, in TorchScript and in ONNX Runtime, and through
lbo.Observer; covariances and the RTS smoother of every filter."""

import numpy as np
import pytest
import torch

from lbo.core.errors import LboError
from lbo.filters import measure
from lbo.models.filternet import WindowFilter
from lbo.models.net import WindowNet
from lbo.models.recursive import START_SCALE, STATE_NAMES, RecursiveFilter
from lbo.serve.engines import TOLERANCE
from lbo.serve.observer import Observer
from lbo.sim.columns import RECEIVER

pytestmark = pytest.mark.usefixtures("one_torch_thread")

VARIANTS = {"plain": {}, "fixes": {"in_features": 6},
            "residual": {"residual": 16, "input_terms": True},  # the inputs' terms learned too
            "single_track_drift": {"body": "single_track", "drift": True}}


def _observer_net(kind: str, window: int = 60, seed: int = 0) -> WindowNet:
    """A window filter whose learned parts are not at their zero start: every weight moved."""
    torch.manual_seed(seed)
    net = WindowNet("filternet", window, features="frame", fixes=kind == "fixes",
                      **VARIANTS[kind])
    with torch.no_grad():
        for p in net.net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return net


def _net(kind: str, window: int = 60, seed: int = 0) -> WindowFilter:
    return _observer_net(kind, window, seed).net


def _logs(g: int, t: int, fixes: bool, seed: int = 1,
          gap: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """G noisy logs of a car turning gently, (G, T, 3) and (G, T, 2); with ``fixes``, two of
    three rows and rows 101 to 99 + ``gap`` have no fix, and the first fix comes at row 3."""
    rng = np.random.default_rng(seed)
    k = np.arange(t)
    psi = 0.002 * k[None, :] + rng.uniform(-3, 3, (g, 1))
    x = np.cumsum(0.2 * np.cos(psi), 1) + 1000.0
    y = np.cumsum(0.2 * np.sin(psi), 1) - 500.0
    m = np.stack([x, y, psi], -1) + rng.normal(size=(g, t, 3)) * [1.0, 1.0, 0.0174]
    m[..., 2] = (m[..., 2] + np.pi) % (2 * np.pi) - np.pi
    u = np.stack([np.full((g, t), 10.0), np.full((g, t), 0.002 * 2.7 / 0.2)], -1)
    if fixes:
        m[:, (k % 3 != 0) | ((k > 100) & (k < 100 + gap)) | (k < 3)] = np.nan
    return m, u


def test_rows_without_a_measurement_coast_to_the_numbers_of_one_step_each():
    """A log's run takes each stretch of rows without any measurement in one coast
    (RecursiveFilter.coast): the poses and covariances of one step per row, in chunks of
    coast_limit rows (a 70-row gap at N=60), on every engine. The net is the one whose ONNX
    step test_torchscript_and_onnx_steps_equal_pytorch[fixes] checks: one export for both."""
    net = _observer_net("fixes")
    rec = RecursiveFilter(net.net)
    assert rec.coasts and rec.coast_limit == 59
    assert not any(RecursiveFilter(_net(kind)).coasts for kind in VARIANTS if kind != "fixes")
    m, u = _logs(1, 300, True, gap=70)
    with torch.no_grad():
        est, cov, _ = rec.run(torch.from_numpy(m), torch.from_numpy(u))  # one step per row
    for engine in ("torch", "onnx"):
        obs = Observer.from_net(net, form="recursive", engine=engine)
        coasted, coast = [], obs._runner.coast
        obs._runner.coast = (lambda u, state, seen=coasted, inner=coast:
                             seen.append(len(u)) or inner(u, state))
        got, valid = found = obs.run(m[0], u[0])
        got_cov = found.cov
        assert sum(coasted) == np.isnan(m[0, 3:, 0]).sum()  # every empty row once started
        # ONNX Runtime's float32 kernels in the noise model: within the export's tolerance
        atol = 1e-12 if engine == "torch" else TOLERANCE
        np.testing.assert_allclose(got, est[0].numpy(), rtol=0, atol=atol, equal_nan=True)
        np.testing.assert_allclose(got_cov, cov[0].numpy(), rtol=0, atol=atol, equal_nan=True)
        assert valid.sum() == np.isfinite(est[0, :, 0].numpy()).sum()
    with pytest.raises(ValueError, match="coast takes 1 to coast_limit rows"):
        rec.coast(torch.from_numpy(u[0, :60]), *rec.initial_state(1))


@pytest.mark.parametrize("kind", list(VARIANTS))
def test_a_batch_run_gives_what_stepping_one_sample_at_a_time_gives(kind):
    net = _observer_net(kind)
    rec = RecursiveFilter(net.net)
    m, u = _logs(3, 300, kind == "fixes")
    with torch.no_grad():
        est, cov, body = rec.run(torch.from_numpy(m), torch.from_numpy(u))
    obs = Observer.from_net(net, form="recursive")
    # the single-track body's [v_y, r], beta = atan2(v_y, V); nothing for a kinematic body
    assert obs.carries_lateral == (kind == "single_track_drift")
    for g in range(3):
        obs.reset()
        steps = [obs.step(None if np.isnan(m[g, k, 0]) else m[g, k], u[g, k])
                 for k in range(300)]
        stepped = np.array([s.state for s in steps])
        np.testing.assert_allclose(stepped, est[g].numpy(), atol=1e-6, equal_nan=True)
        np.testing.assert_allclose(np.array([s.cov for s in steps]), cov[g].numpy(),
                                   atol=1e-6, equal_nan=True)
        lateral = np.array([s.lateral for s in steps])
        np.testing.assert_allclose(lateral, obs.run(m[g], u[g]).lateral, atol=1e-9,
                                   equal_nan=True)
        if obs.carries_lateral:
            b = body[g].numpy()
            np.testing.assert_allclose(lateral, np.column_stack(
                [np.arctan2(b[:, 0], u[g, :, 0]), b]), atol=1e-9)
        else:
            assert np.isnan(lateral).all()
    first = int(np.argmax(np.isfinite(m[0, :, 0])))
    assert np.isnan(est[0, :first].numpy()).all() and np.isfinite(est[0, first:].numpy()).all()


@pytest.mark.parametrize("kind", list(VARIANTS))
def test_a_step_in_inference_leaves_out_what_no_filter_uses_and_keeps_every_bit(kind,
                                                                                  monkeypatch):
    """In inference a step skips the start where no filter of the batch starts, the NaN where
    all have started, and the receiver's R where no row has an accuracy or a course: the
    numbers of the one graph that tracing and training take (with gradients), to the last
    bit, for a batch whose filters start at different rows and alone."""
    fixes = kind == "fixes"
    m, u = _logs(2, 120, fixes)
    rows = np.concatenate([m, np.full(m.shape[:2] + (5,), np.nan)], -1)
    if fixes:
        rows[1, :20] = np.nan  # the second log starts later
        rows[0, 30:50, 3:5] = 0.8  # a receiver's accuracy
        rows[1, 60:70, 2], rows[1, 60:70, 6:8] = np.nan, (0.3, 0.05)  # a course, no heading
    rec = RecursiveFilter(_net(kind))
    calls, inner = [], rec._step_cov
    monkeypatch.setattr(rec, "_step_cov", lambda *a: calls.append(1) or inner(*a))

    def steps(batch: list[int]) -> list[np.ndarray]:
        state, out = rec.initial_state(len(batch)), []
        for k in range(rows.shape[1]):
            pose, cov, *state = rec(torch.from_numpy(rows[batch, k]),
                                    torch.from_numpy(u[batch, k]), *state)
            out += [t.detach().numpy().copy() for t in (pose, cov, *state)]
        return out

    for batch in ([0, 1], [0], [1]):
        with torch.enable_grad():
            graph, graph_calls = steps(batch), len(calls)
        calls.clear()
        with torch.inference_mode():
            lean, lean_calls = steps(batch), len(calls)
        calls.clear()
        for a, b in zip(graph, lean, strict=True):
            np.testing.assert_array_equal(a, b)
        assert graph_calls == 2 * rows.shape[1] and lean_calls < graph_calls / 2


@pytest.mark.parametrize("kind", list(VARIANTS))
def test_torchscript_and_onnx_steps_equal_pytorch(kind):
    m, u = _logs(1, 200, kind == "fixes", seed=2)
    net = _observer_net(kind)
    runs = {e: Observer.from_net(net, engine=e, form="recursive").run(m[0], u[0])
            for e in ("torch", "torchscript", "onnx")}
    for engine in ("torchscript", "onnx"):
        for part in ("state", "cov", "lateral"):  # lateral: the single-track body's
            np.testing.assert_allclose(getattr(runs[engine], part),
                                       getattr(runs["torch"], part), atol=1e-6, equal_nan=True)
    assert np.isfinite(runs["onnx"].lateral).all() == (kind == "single_track_drift")


def test_its_cost_and_state_do_not_grow_with_the_log():
    rec = RecursiveFilter(_net("single_track_drift", window=400))
    state = rec.initial_state(1)
    sizes = [s.numel() for s in state]
    m, u = _logs(1, 1000, False, seed=3)
    with torch.no_grad():
        for k in range(1000):
            _, _, *state = rec(torch.from_numpy(m[:, k]), torch.from_numpy(u[:, k]), *state)
    assert [s.numel() for s in state] == sizes  # a ring of N slots, whatever the log's length
    assert len(state) == len(STATE_NAMES) and state[STATE_NAMES.index("k")].item() == 1000
    # the running sums are the sums of what the ring holds: nothing drifts out of step
    ring, sums = state[STATE_NAMES.index("ring")], state[STATE_NAMES.index("sums")]
    np.testing.assert_allclose(ring.sum(1).numpy(), sums.numpy(), rtol=1e-9)


@pytest.mark.parametrize("kind", ["residual", "single_track_drift"])
def test_on_a_window_the_recursive_form_is_the_window_filter_told_one_noise_level(kind,
                                                                                   monkeypatch):
    # over exactly one window from the cold start, both forms are the same EKF; they differ
    # only in the noise statistic (the window's whole against the running one) and in the
    # frame their noise is along and across (the window's last fix's heading against each
    # step's latest), so hold the noise model's output fixed, make Q the same along as across,
    # and compare; and start both at P = R (the recursive form starts wider, START_SCALE R,
    # as it cannot know the noise level at its first fix)
    monkeypatch.setattr("lbo.models.recursive.START_SCALE", 1.0)
    net = _net(kind, window=80)
    with torch.no_grad():
        net.noise[-1].weight.zero_()
        net.noise[-1].bias.zero_()
        net.log_q_scale[1] = net.log_q_scale[0]
    m, u = _logs(4, 80, False, seed=4)
    sigma = torch.tensor([1.0, 1.0, 0.0174], dtype=torch.float64)
    net.measurement_sigma = lambda x: sigma.expand(len(x), 3).to(x.dtype)  # window form
    rec = RecursiveFilter(net)
    rec._noise = lambda sums, speed, heading: torch.diag(sigma**2).expand(len(sums), 3, 3)
    with torch.no_grad():
        est = rec.run(torch.from_numpy(m), torch.from_numpy(u)).pose
        x = torch.from_numpy(np.concatenate([m, u], -1))
        window = net.double()(x)  # world coordinates in, world out: the filter is equivariant
    np.testing.assert_allclose(est[:, -1].numpy(), window.numpy(), atol=1e-6)


def test_form_is_checked_in_one_line():
    cnn = WindowNet("cnn", 20)
    with pytest.raises(LboError, match="form=recursive: a WindowCNN has no filter"):
        Observer.from_net(cnn, form="recursive")
    with pytest.raises(LboError, match=r"form must be one of \['window', 'recursive'\]"):
        Observer.from_net(WindowNet("filternet", 20, features="frame"), form="kalman")
    with pytest.raises(LboError, match="smooth: cnn-N20 has no filter to smooth"):
        Observer.from_net(cnn).run(*(a[0] for a in _logs(1, 50, False)), smooth=True)


@pytest.mark.parametrize("kind", list(VARIANTS))
def test_estimates_move_and_turn_with_the_log(kind):
    # the noise model reads, and its R and Q act, along and across the latest fix's heading:
    # shift and turn a whole log, and the estimates shift and turn with it
    rec = RecursiveFilter(_net(kind))
    m, u = _logs(2, 250, kind == "fixes", seed=5)
    theta, shift = 0.8, np.array([500.0, -250.0])
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    moved = np.concatenate([m[..., :2] @ rot.T + shift, m[..., 2:] + theta], -1)
    with torch.no_grad():
        est, cov = (t.numpy() for t in rec.run(torch.from_numpy(m), torch.from_numpy(u))[:2])
        est_m, cov_m = (t.numpy()
                        for t in rec.run(torch.from_numpy(moved), torch.from_numpy(u))[:2])
    np.testing.assert_allclose(est_m[..., :2], est[..., :2] @ rot.T + shift, atol=1e-6)
    turned = np.einsum("ij,gtjk,lk->gtil", rot, cov[..., :2, :2], rot)
    np.testing.assert_allclose(cov_m[..., :2, :2], turned, atol=1e-9, equal_nan=True)


def test_export_writes_the_step_function_a_control_loop_calls(tmp_path):
    # the files of the recursive form, called as the JSON says, give Observer.step's numbers
    import json

    import onnxruntime as ort

    from lbo.export import export

    net = _observer_net("fixes", window=60)
    obs = Observer.from_net(net)
    paths = export(obs, tmp_path, "robust")
    spec = json.loads(paths["json"].read_text())
    # the nets run in float32 inside the float64 filter; ONNX Runtime's float32 kernels round
    # apart from torch's by an ulp, which the filter carries: within the export's tolerance
    assert spec["form"] == "recursive" and spec["max_abs_diff_to_pytorch"]["onnx"] < TOLERANCE
    session = ort.InferenceSession(str(paths["onnx"]), providers=["CPUExecutionProvider"])
    script = torch.jit.load(str(paths["torchscript"]))
    state = {s["name"]: np.zeros([1 if d == "batch" else d for d in s["shape"]])
             for s in spec["state"]}
    ts_state = [torch.from_numpy(v.copy()) for v in state.values()]
    inputs = {s["name"] for s in spec["state"] if s["onnx_input"]}
    assert spec["input"]["m"]["columns"] == list(measure.CHANNELS)
    m, u = _logs(1, 120, True, seed=6)
    rows = measure.widen(m)
    # the second half as a single antenna gives it: no heading, an accuracy with each fix
    rows[0, 60:, 2] = np.nan
    rows[0, 60:, 3:5] = np.where(np.isfinite(rows[0, 60:, :1]), 0.7, np.nan)
    receiver = np.full((120, len(RECEIVER)), np.nan)
    receiver[:, :2] = rows[0, :, 3:5]
    for k in range(120):
        fix = rows[0, k, :3]
        want = obs.step(None if np.isnan(fix[0]) else fix, u[0, k], receiver=receiver[k])
        out = session.run(None, {"m": rows[:, k], "u": u[:, k],
                                 **{n: v for n, v in state.items() if n in inputs}})
        state = dict(zip(state, out[2:]))
        with torch.no_grad():
            ts = script(torch.from_numpy(rows[:, k]), torch.from_numpy(u[:, k]), *ts_state)
        ts_state = list(ts[2:])
        for pose, cov in ((out[0][0], out[1][0]), (ts[0][0].numpy(), ts[1][0].numpy())):
            if want.valid:
                np.testing.assert_allclose(pose[:2], want.state[:2], atol=TOLERANCE)
                np.testing.assert_allclose(cov, want.cov, rtol=1e-5, atol=1e-12)
            else:
                assert np.isnan(pose).all()


# --------------------------------------------------------------------------- a receiver's rows


def _joseph(z, P, y, H, R):
    """The Kalman update with the held channels alone, written out: H (p, 3), R (p, p)."""
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    A = np.eye(3) - K @ H
    return z + K @ y, A @ P @ A.T + K @ R @ K.T


def test_a_receivers_row_updates_with_the_channels_it_holds():
    """Start at a fix without a heading and a course; then a position alone, a course alone,
    each against the update with those channels alone, written out by hand; a full paper row
    gives the same numbers as its 8-wide form."""
    rec = RecursiveFilter(_net("fixes"))
    rec.keep_prior = True  # each step's prior, to write the update out against
    nan = np.nan
    rows = np.array([[5.0, -3.0, nan, 0.4, 0.6, nan, 0.3, 0.05],   # position + course
                     [nan] * 8,                                     # a prediction
                     [7.1, -2.2, nan, 0.5, 0.7, nan, nan, nan],     # a position alone
                     [nan, nan, nan, nan, nan, nan, 0.33, 0.02]])   # a course alone
    u = torch.tensor([[8.0, 0.01]], dtype=torch.float64)
    state = rec.initial_state(1)
    with torch.no_grad():
        pose, cov, *state = rec(torch.from_numpy(rows[:1]), u, *state)
        np.testing.assert_allclose(pose[0].numpy(), [5.0, -3.0, 0.3], rtol=0, atol=1e-15)
        np.testing.assert_allclose(cov[0].numpy(), np.diag([0.16, 0.36, 0.0025]), rtol=1e-15)
        for row, H, R, y_of in (
                (rows[1], None, None, None),
                (rows[2], np.eye(3)[:2], np.diag([0.25, 0.49]), lambda z: rows[2, :2] - z[:2]),
                (rows[3], np.eye(3)[2:], np.array([[0.02**2]]),
                 lambda z: np.array([(rows[3, 6] - z[2] + np.pi) % (2 * np.pi) - np.pi]))):
            pose, cov, *state = rec(torch.from_numpy(row[None]), u, *state)
            z_pred, P_pred = (t[0].numpy() for t in rec.last_prior[:2])
            if H is None:  # a row of nothing: the prediction (its heading wrapped)
                np.testing.assert_allclose(pose[0].numpy(), z_pred, rtol=0, atol=1e-15)
                continue
            z, P = _joseph(z_pred, P_pred, y_of(z_pred), H, R)
            np.testing.assert_allclose(pose[0].numpy(), z, rtol=0, atol=1e-12)
            np.testing.assert_allclose(cov[0].numpy(), P, rtol=0, atol=1e-12)
        full = np.array([[8.0, -1.9, 0.32]])
        wide = np.concatenate([full, np.full((1, 5), nan)], 1)
        a = rec(torch.from_numpy(full), u, *[s.clone() for s in state])
        b = rec(torch.from_numpy(wide), u, *[s.clone() for s in state])
    for p, q in zip(a, b):
        np.testing.assert_array_equal(p.numpy(), q.numpy())


def test_the_recursive_form_takes_a_single_antenna_log():
    """A simulated single-antenna log (1 Hz fixes without a heading, their accuracies, GNSS
    velocities): estimates from the first course over ground on, stepping as the batch run,
    within 1.5 times the EKF's heading error on the same rows (the untrained window filter's
    noise is the paper's, as the EKF's). Where it cannot take them: one line."""
    from conftest import compose_cfg

    from lbo.simulate import simulate

    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom", "receiver=single_antenna"])).head(
        1500)
    m = df[["x_m", "y_m", "psi_m"]].to_numpy(float)
    u = df[["V", "delta"]].to_numpy(float)
    z = df[["x", "y", "psi"]].to_numpy(float)
    r = df.reindex(columns=list(RECEIVER)).to_numpy(float)
    assert np.isnan(m[:, 2]).all() and np.isfinite(m[:, 0]).sum() < len(m) / 40
    # test_torchscript_and_onnx_steps_equal_pytorch's [fixes] net: its ONNX step is kept
    # (lbo's cache folder), so this test reads the export rather than making it again
    net = _observer_net("fixes")
    obs = Observer.from_net(net, form="recursive")
    assert obs.takes_receiver
    est, valid = obs.run(m, u, receiver=r)
    first = int(np.argmax(np.isfinite(m[:, 0]) & np.isfinite(r[:, RECEIVER.index("ve_m")])))
    assert not valid[:first].any() and valid[first:].all()
    stepped = np.array([obs.step(mk, uk, receiver=rk).state for mk, uk, rk in zip(m, u, r)])
    np.testing.assert_allclose(stepped, est, rtol=0, atol=1e-9, equal_nan=True)
    ekf, ok = Observer.load("ekf").run(m, u, receiver=r)
    rows = valid & ok

    def psi(e):
        d = (e[rows, 2] - z[rows, 2] + np.pi) % (2 * np.pi) - np.pi
        return float(np.sqrt(np.mean(d ** 2)))

    print("psi rmse: recursive", psi(est), "ekf", psi(ekf))
    assert psi(est) < 1.5 * psi(ekf)
    for engine in ("torchscript", "onnx"):  # the exported step reads the same rows
        exported = Observer.from_net(net, form="recursive", engine=engine)
        assert exported.takes_receiver, engine
        np.testing.assert_allclose(exported.run(m, u, receiver=r)[0], est, rtol=0,
                                   atol=TOLERANCE, equal_nan=True, err_msg=engine)
    blind = WindowNet("filternet", 60, features="frame")  # trained with a fix at every step
    for refused, where in ((Observer.from_net(net, form="window"), "window form"),
                           (Observer.from_net(blind, form="recursive"), "no missing fixes")):
        assert not refused.takes_receiver, where
        with pytest.raises(LboError, match=r"^receiver: filternet-N60 does not take a "
                                           r"receiver's channels; the classical observers"):
            refused.run(m, u, receiver=r)


@pytest.mark.parametrize("fixes", [False, True])
def test_an_empty_statistic_gets_its_own_learned_r_with_learned(fixes):
    """``model.empty_statistic=learned``: where the noise statistic holds nothing yet (the
    recursive form's first fix; a window with fewer than two fixes) R is the filter's own
    ``log_empty_sigma`` (here e times alpha = 1's), which learns from there, and no gradient
    reaches the noise model; ``net`` (the default, whose checkpoints hold no such parameter)
    asks the noise model, here set to say e^2 times alpha's sigma. Elsewhere the two agree."""
    r0 = torch.exp(_net("plain").log_r0).double()
    starts, windows, grads = {}, {}, {}
    for mode in ("net", "learned"):
        net = WindowNet("filternet", 40, features="frame", fixes=fixes,
                        empty_statistic=mode).net
        with torch.no_grad():
            net.noise[-1].bias.fill_(2.0)
            net.log_empty_sigma.add_(1.0)
        assert ("log_empty_sigma" in net.state_dict()) == (mode == "learned")
        rec = RecursiveFilter(net)
        m = torch.tensor([[3.0, -2.0, 0.4]], dtype=torch.float64)
        _, cov, *_ = rec(m, torch.tensor([[8.0, 0.0]], dtype=torch.float64),
                         *rec.initial_state(1))
        starts[mode] = cov[0]
        sigma = net.noise_sigma(torch.zeros(2, 3), torch.zeros(2, 1 + fixes),
                                torch.tensor([True, False]))
        grads[mode] = torch.autograd.grad(sigma[0].sum(), net.noise[-1].bias)[0]
        windows[mode] = sigma.detach().double()
    want = START_SCALE * torch.diag(r0 ** 2)
    torch.testing.assert_close(starts["learned"], want * np.exp(2.0))
    torch.testing.assert_close(starts["net"], want * np.exp(4.0))
    torch.testing.assert_close(windows["learned"][0], r0 * np.exp(1.0), rtol=1e-6, atol=0)
    torch.testing.assert_close(windows["net"][0], r0 * np.exp(2.0), rtol=1e-6, atol=0)
    torch.testing.assert_close(windows["learned"][1], windows["net"][1])
    assert grads["learned"].abs().max() == 0 < grads["net"].abs().max()
    with pytest.raises(LboError, match=r"^model.empty_statistic: expected one of \['net', "
                                       r"'learned'\], got 'zero'$"):
        WindowNet("filternet", 40, features="frame", empty_statistic="zero")
