"""The rank a certified low-rank GP variance would need, from the spectrum of K
(docs/performance.md, "The certified low-rank variance, measured").

For one output, K = U diag(λ) Uᵀ and A = (K + σ²I)⁻¹ = (I − U diag(λ/(λ+σ²)) Uᵀ)/σ². Keeping the r
largest directions of the correction, the variance error at any input z is
e = Σ_{i>r} λ_i (u_iᵀk)² / (σ²(λ_i + σ²)), and since Σ_i (u_iᵀk)²/λ_i = kᵀK⁺k ≤ k(z, z) = σ_f²,
e ≤ λ_{r+1}² σ_f² / (σ² (λ_{r+1} + σ²)) for every z: a certificate that needs no particle. This
prints, per output, the smallest r whose certificate is below tol·σ_n² (docs/performance.md).

    python benchmarks/variance_rank.py
"""
import numpy as np, jax, jax.numpy as jnp
import pipps
from pipps.studies import load_snapshot
from pipps.gp.kernel import se_ard
pipps.enable_float64()
for f,t in (("tp_thesis_s1",10),("tp_thesis_s0",7),("pilco_thesis_s2",9)):
    snap = load_snapshot(f"results/thesis/cartpole_swingup_angle_k1_{f}.h5", t)
    post = snap.model; n = snap.num_points
    h = post.hyper
    x = np.asarray(post.inputs[:n])
    print(f, "trial", t, "N", n, "M", post.inputs.shape[0])
    for a in range(4):
        K = np.asarray(se_ard(jnp.asarray(x), jnp.asarray(x), h.log_lengthscale[a], h.log_signal[a]))
        lam = np.clip(np.linalg.eigvalsh(K)[::-1], 0, None)
        sf2 = float(np.exp(2*h.log_signal[a])); s2 = float(np.exp(2*h.log_noise[a]))
        b = lam**2*sf2/(s2*(lam+s2))/s2   # bound if tail starts at index i (rel to sigma_n^2)
        rs = {tol: int(np.argmax(b <= tol)) if np.any(b<=tol) else n for tol in (1e-2,1e-4,1e-6,1e-8)}
        print(f"  out {a}: sf2/sn2={sf2/s2:.1e}  #lam>0.1s2={int(np.sum(lam>0.1*s2))}  r(tol)={rs}")
