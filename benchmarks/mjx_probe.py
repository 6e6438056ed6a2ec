"""Probe MuJoCo MJX: compile and run times of a ball-and-wall scene, its forward-mode gradient against
central differences, and what reverse mode says (docs/contact.md, "MuJoCo MJX here").

    taskset -c 1 python benchmarks/mjx_probe.py STEPS SOLVER_ITERATIONS     # e.g. 100 4

A ball on a free joint launched at (3, 3) m/s toward a box wall, STEPS steps of 10 ms in one
``lax.scan``; the gradient of its final x with respect to the launch velocity.
"""
import sys, time
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import mujoco
from mujoco import mjx

steps = int(sys.argv[1]) if len(sys.argv) > 1 else 20
iters = sys.argv[2] if len(sys.argv) > 2 else "4"
xml = f'''<mujoco><option timestep="0.01" iterations="{iters}" ls_iterations="4" gravity="0 0 -9.81"/>
<worldbody><geom name="wall" type="box" size="0.05 0.5 0.25" pos="1 0 0.25"/>
<geom type="plane" size="5 5 0.1"/>
<body name="ball" pos="0 0 0.1"><freejoint/><geom type="sphere" size="0.05" mass="1"/></body></worldbody></mujoco>'''
m = mujoco.MjModel.from_xml_string(xml)
mx = mjx.put_model(m)
d0 = mjx.make_data(mx)

def final_x(v0):
    qvel = d0.qvel.at[0].set(v0[0]).at[2].set(v0[1])
    d = d0.replace(qvel=qvel)
    def body(d, _):
        return mjx.step(mx, d), None
    d, _ = jax.lax.scan(body, d, None, length=steps)
    return d.qpos[0]

v = jnp.array([3.0, 3.0])
t = time.time(); f = jax.jit(final_x); y = f(v).block_until_ready(); print(f"forward {steps} steps: compile+run {time.time()-t:.1f}s, x={float(y):.4f}", flush=True)
t = time.time(); y = f(v).block_until_ready(); print(f"  run {time.time()-t:.4f}s", flush=True)
t = time.time(); jf = jax.jit(jax.jacfwd(final_x)); g = jf(v).block_until_ready(); print(f"jacfwd: compile+run {time.time()-t:.1f}s, grad={g}", flush=True)
t = time.time(); g = jf(v).block_until_ready(); print(f"  run {time.time()-t:.4f}s", flush=True)
eps = 1e-5
fd = [(f(v.at[i].add(eps)) - f(v.at[i].add(-eps))) / (2 * eps) for i in range(2)]
print("finite difference", [float(a) for a in fd], flush=True)
try:
    t = time.time(); gr = jax.jit(jax.grad(final_x))(v); print(f"grad (reverse): {gr} in {time.time()-t:.1f}s")
except Exception as e:
    print("reverse mode:", type(e).__name__, str(e).splitlines()[0][:300])
