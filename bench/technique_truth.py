"""Across-seed efficiency of path tracing and bdpt on one scene: the truth the technique
pilot (tessera_render::pilot) is checked against (docs/benchmarks.md, "Technique pilot").

pip install numpy OpenEXR
python3 bench/technique_truth.py target/release/tessera builtin:caustic 32 32 256 128 24 --max-depth 12
arguments: BINARY SCENE WIDTH HEIGHT PATH_SPP BDPT_SPP SEEDS [extra render flags]
"""
import OpenEXR, numpy as np, subprocess, sys, re
def lum(path):
    a=np.asarray(OpenEXR.File(path).channels()["RGB"].pixels,dtype=np.float64)
    return 0.2126*a[...,0]+0.7152*a[...,1]+0.0722*a[...,2]
b=sys.argv[1]; scene=sys.argv[2]; w,h=sys.argv[3],sys.argv[4]; pspp,bspp=sys.argv[5],sys.argv[6]; n=int(sys.argv[7])
extra=sys.argv[8:]
res={}
for integ,spp in [("path",pspp),("bdpt",bspp)]:
    imgs=[];cpu=0
    for seed in range(1,n+1):
        out=subprocess.run([b,"render",scene,"--integrator",integ,"--width",w,"--height",h,"--spp",spp,"--seed",str(seed),"--threads","1","-o","/tmp/t.exr"]+extra,capture_output=True,text=True).stdout
        cpu+=float(re.search(r"cpu seconds: ([0-9.]+)",out).group(1))
        imgs.append(lum("/tmp/t.exr"))
    res[integ]=(np.array(imgs),cpu/n)
pooled=0.5*(res["path"][0].mean(0)+res["bdpt"][0].mean(0))
scale=np.maximum(pooled,0.1*pooled.mean())
eff={}
for k,(I,c) in res.items():
    v=I.var(0,ddof=1)/scale**2
    # median over seeds of per-render relMSE vs pooled mean (typical render)
    typ=np.median([(((x-pooled)/scale)**2).mean() for x in I])
    eff[k]=1/(v.mean()*c)
    print(f"{k}: spp {dict(path=pspp,bdpt=bspp)[k]} cpu {c:.3f} s, mean rel variance {v.mean():.4f} (max pixel {v.max():.3f}), efficiency {eff[k]:.1f}; typical render relMSE {typ:.4f}, typical efficiency {1/(typ*c):.1f}")
print(f"path/bdpt efficiency: {eff['path']/eff['bdpt']:.2f}x")
