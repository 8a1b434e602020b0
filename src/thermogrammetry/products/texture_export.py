"""Exports of a :class:`~thermogrammetry.products.texture.TextureResult`, as bytes/text (no paths).

* glTF binary (GLB) and OBJ + MTL with a palette-rendered preview PNG (the palette covers the
  textured range; gutter texels take their nearest chart colour so that filtering shows no dark seams,
  the temperature TIFFs are never filled);
* the float32 temperature texture (K or °C) and its 16-bit encoding (``value = code · scale + offset``,
  code 0 = no data; GDAL metadata), the int32 source-image texture (−1 = none) and the viewing-angle
  texture (degrees), TIFF; for frames in raw sensor counts the same two files hold counts, labelled
  ``counts`` / ``raw_counts`` (:func:`counts_float_tiff_bytes`, :func:`counts_u16_tiff_bytes`);
* PLY with per-vertex ``temperature_k`` (or ``raw_counts``; NaN where no image sees the vertex);
* a rendered view of the textured mesh (ray cast from a virtual camera) for reports.

UV convention: the atlas stores ``v`` from the top row; OBJ writes ``vt u (1 − v)`` (OBJ's origin is the
bottom-left), glTF keeps ``v`` (its origin is the top-left).
"""

from __future__ import annotations

import io
import json

import numpy as np

from ..radiometry.encoding import from_kelvin

__all__ = ["preview_rgb", "palette_range", "palette_png_text", "png_bytes", "glb_bytes", "obj_text", "mtl_text", "ply_bytes",
           "int32_tiff_bytes", "float32_tiff_bytes", "counts_float_tiff_bytes", "counts_u16_tiff_bytes", "render_view",
           "texture_json", "viewer_html"]


def palette_range(t) -> tuple[float, float]:
    """The preview palette's range: 1st and 99th percentile of the finite values (any unit)."""
    return _palette_range(t)


def _palette_range(t):
    fin = t[np.isfinite(t)]
    if not len(fin):
        return 0.0, 1.0
    lo, hi = np.percentile(fin, [1, 99])
    return float(lo), float(max(hi, lo + 1e-3))


def preview_rgb(temperature, *, vmin=None, vmax=None, cmap="inferno", fill_gutter: int = 4):
    """(H, W, 3) uint8 palette image of a temperature texture (any unit); NaN texels grey (128) after
    ``fill_gutter`` dilation steps that copy the nearest textured colour outward (display only)."""
    import matplotlib

    t = np.asarray(temperature, float)
    lo, hi = _palette_range(t)
    lo = lo if vmin is None else vmin
    hi = hi if vmax is None else vmax
    cm = matplotlib.colormaps[cmap]
    rgb = (cm(np.clip((np.nan_to_num(t, nan=lo) - lo) / (hi - lo), 0, 1))[..., :3] * 255).astype(np.uint8)
    have = np.isfinite(t)
    for _ in range(int(fill_gutter)):  # dilate colours into the gutter
        new = have.copy()
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            src = np.roll(have, (dy, dx), axis=(0, 1))
            take = src & ~new
            rgb[take] = np.roll(rgb, (dy, dx), axis=(0, 1))[take]
            new |= take
        have = new
    rgb[~have] = 128
    return rgb


def palette_png_text(palette: dict) -> dict:
    """PNG text chunks that label a preview's colour scale (``palette``: colormap, label, unit, min, max)."""
    return {"Description": f"thermogrammetry texture preview: {palette['colormap']} colours over {palette['label']} "
                           f"{palette['min']:.6g} .. {palette['max']:.6g} ({palette['unit']})",
            "thermogrammetry:quantity": str(palette.get("quantity", "")),
            "thermogrammetry:unit": str(palette["unit"]),
            "thermogrammetry:palette": json.dumps(palette)}


def png_bytes(rgb, text: dict | None = None) -> bytes:
    """PNG of an (H, W, 3) uint8 image; ``text``: tEXt chunks (key -> str), e.g. :func:`palette_png_text`."""
    import cv2

    if text:
        from PIL import Image
        from PIL.PngImagePlugin import PngInfo

        info = PngInfo()
        for k, v in text.items():
            info.add_text(k, v)
        buf = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(rgb, np.uint8)).save(buf, format="PNG", pnginfo=info)
        return buf.getvalue()

    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    return buf.tobytes()


#: how the GLB's positions map back to the survey's CRS (stored in the asset's extras)
GLB_AXES = ("glTF +X = east, +Y = up, +Z = south (Y-up, right-handed) about a local origin: "
            "CRS (x, y, z) = (X + offset_x, -Z + offset_y, Y + offset_z)")


def glb_bytes(result, preview, extras: dict | None = None, crs: str | None = None) -> bytes:
    """Binary glTF of the atlas mesh with the preview as its base-colour texture, unlit (``KHR_materials_unlit``:
    viewers show the palette's colours unshaded, so that they read against the palette's legend).

    Positions are Y-up (glTF's convention: a viewer shows the model upright) about a local origin with no node
    transform (float32 keeps sub-millimetre steps; the model sits at the viewer's origin, not kilometres away):
    glTF ``(X, Y, Z) = (x − ox, z − oz, −(y − oy))``. The offset ``(ox, oy, oz)`` (m), ``crs`` and the axes
    (:data:`GLB_AXES`) are in the asset's ``extras["thermogrammetry"]``.
    ``extras``: stored as the mesh's glTF ``extras`` under ``thermogrammetry_palette`` (what the colours mean)."""
    import trimesh
    from PIL import Image

    from .texture_mesh import local_origin

    at = result.atlas
    # glTF positions are float32: 0.25-0.5 m steps at projected-CRS coordinates (EPSG:2056, UTM). They are
    # stored relative to the mesh's local origin and the node's translation (a JSON double) adds it back.
    origin = local_origin(result.vertices)
    L = result.vertices[at.vmapping] - origin
    V = np.column_stack([L[:, 0], L[:, 2], -L[:, 1]])  # z-up survey frame -> glTF Y-up
    uv = at.uv.copy()
    uv[:, 1] = 1.0 - uv[:, 1]  # trimesh takes OpenGL uv (origin bottom-left) and flips for glTF
    mat = trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(preview), metallicFactor=0.0,
                                              roughnessFactor=1.0, doubleSided=True)
    mesh = trimesh.Trimesh(V, at.faces, visual=trimesh.visual.TextureVisuals(uv=uv, material=mat), process=False)
    if extras:
        mesh.metadata["thermogrammetry_palette"] = dict(extras)
    scene = trimesh.Scene()
    scene.add_geometry(mesh, node_name="textured", geom_name="textured")
    info = {"offset": [float(o) for o in origin], "crs": crs, "axes": GLB_AXES, "unit": "m"}
    return _with_asset_extras(scene.export(file_type="glb"), {"thermogrammetry": info}, unlit=True)


def _with_asset_extras(glb: bytes, extras: dict, *, unlit: bool = False) -> bytes:
    """The GLB with ``asset.extras`` set (its JSON chunk rewritten, padded to 4 bytes with spaces).

    ``unlit``: every material also gets the ``KHR_materials_unlit`` extension (listed in ``extensionsUsed``; viewers
    without it fall back to the PBR base colour): the preview colours are data (the palette of a legend), so a viewer
    shows them as they are, without its lights shading them."""
    import json
    import struct

    n_json, kind = struct.unpack_from("<II", glb, 12)
    assert kind == 0x4E4F534A, "first GLB chunk must be JSON"
    doc = json.loads(glb[20:20 + n_json].decode("utf-8"))
    doc.setdefault("asset", {"version": "2.0"}).setdefault("extras", {}).update(extras)
    if unlit and doc.get("materials"):
        for m in doc["materials"]:
            m.setdefault("extensions", {})["KHR_materials_unlit"] = {}
        used = doc.setdefault("extensionsUsed", [])
        if "KHR_materials_unlit" not in used:
            used.append("KHR_materials_unlit")
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    rest = glb[20 + n_json:]
    total = 12 + 8 + len(js) + len(rest)
    return struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js + rest


def obj_text(result, mtl_name: str = "textured.mtl", *, quantity: str = "temperatures") -> str:
    at = result.atlas
    V = result.vertices[at.vmapping]
    lines = [f"# thermogrammetry texture: {quantity} in temperature_texture.tif (preview colours in the PNG)",
             f"mtllib {mtl_name}", "usemtl thermal"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in V]
    lines += [f"vt {u:.7f} {1.0 - v:.7f}" for u, v in at.uv]
    lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in at.faces + 1]
    return "\n".join(lines) + "\n"


def mtl_text(png_name: str = "textured.png") -> str:
    return f"newmtl thermal\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {png_name}\n"


def ply_bytes(vertices, faces, vertex_temperature_k, *, name: str = "temperature_k") -> bytes:
    """Binary PLY: vertices with ``temperature_k`` (float32, NaN = none) and the faces.

    ``name``: the per-vertex property, ``temperature_k`` or ``raw_counts`` (values of count frames, as the cloud)."""
    from plyfile import PlyData, PlyElement

    if name not in ("temperature_k", "raw_counts"):
        raise ValueError(f"ply_bytes: name={name!r}; expected 'temperature_k' or 'raw_counts'")
    V = np.asarray(vertices, float)
    vt = np.zeros(len(V), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), (name, "f4")])
    vt["x"], vt["y"], vt["z"] = V.T
    vt[name] = np.asarray(vertex_temperature_k, np.float32)
    ft = np.zeros(len(faces), dtype=[("vertex_indices", "i4", (3,))])
    ft["vertex_indices"] = np.asarray(faces, np.int32)
    buf = io.BytesIO()
    PlyData([PlyElement.describe(vt, "vertex"), PlyElement.describe(ft, "face")], text=False).write(buf)
    return buf.getvalue()


def int32_tiff_bytes(a) -> bytes:
    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, np.asarray(a, np.int32), compression="zlib")
    return buf.getvalue()


def float32_tiff_bytes(a) -> bytes:
    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, np.asarray(a, np.float32), compression="zlib")
    return buf.getvalue()


def counts_float_tiff_bytes(values) -> bytes:
    """float32 TIFF of a texture of raw sensor counts (NaN = no texel), GDAL unit ``counts``, quantity
    ``raw_counts``, described as "raw sensor counts (not temperature)"."""
    from ..io.tiff import encode_raster_tiff

    return encode_raster_tiff(np.asarray(values, np.float32), unit="counts", quantity="raw_counts",
                              description="raw sensor counts (not temperature), as sampled; NaN = no texel")


def counts_u16_tiff_bytes(values) -> bytes:
    """uint16 TIFF of a texture of raw counts: ``code = round(value)`` clipped to 1..65535 (scale 1, offset 0,
    GDAL metadata), code 0 = no texel; the error is at most 0.5 count (bilinear samples are fractional)."""
    from ..io.tiff import _encode_single_band

    v = np.asarray(values, np.float64)
    fin = np.isfinite(v)
    code = np.zeros(v.shape, np.uint16)
    code[fin] = np.clip(np.rint(v[fin]), 1, 65535).astype(np.uint16)
    band = {"scale": "1.0", "offset": "0.0", "unittype": "counts",
            "description": "raw sensor counts (not temperature) = code * 1 + 0; 0 = no texel"}
    items = {"THERMOGRAMMETRY_QUANTITY": "raw_counts", "THERMOGRAMMETRY_UNIT": "counts", "THERMOGRAMMETRY_ENCODING": "uint16",
             "THERMOGRAMMETRY_MAX_QUANTISATION_ERROR": "0.5"}
    return _encode_single_band(code, 16, 1, "0", band, items, None, "raw sensor counts (not temperature)")


def render_view(result, center, target, *, size=(480, 360), focal_px=None, up=(0, 0, 1)):
    """Ray-cast the textured mesh from a virtual pinhole camera: (H, W) values of the texture (K, or raw counts
    for count frames), NaN for background and untextured texels (nearest texel)."""
    import trimesh

    from ..geometry import Pose
    from .texture_mesh import local_origin
    from .texture_visibility import ray_intersector

    w, h = size
    f = focal_px or 0.9 * w
    pose = Pose.look_at(np.asarray(center, float), np.asarray(target, float), up=up)
    gy, gx = np.mgrid[0:h, 0:w].astype(float)
    d = np.stack([(gx - (w - 1) / 2) / f, (gy - (h - 1) / 2) / f, np.ones_like(gx)], -1).reshape(-1, 3) @ pose.R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origin = local_origin(result.vertices)  # Embree casts in float32: a local frame (texture.local_origin)
    V = result.vertices - origin
    ray = ray_intersector(V, result.faces)
    o = np.broadcast_to(pose.center - origin, d.shape).copy()
    tri = np.asarray(ray.intersects_first(ray_origins=o, ray_directions=d), np.int64)
    out = np.full(len(d), np.nan)
    hit = np.flatnonzero(tri >= 0)
    if len(hit):
        F = result.faces[tri[hit]]
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        t = np.einsum("ij,ij->i", V[F[:, 0]] - o[hit], n) / np.einsum("ij,ij->i", d[hit], n)
        P = o[hit] + t[:, None] * d[hit]
        bary = trimesh.triangles.points_to_barycentric(V[F], P)
        at = result.atlas
        uv = np.einsum("ij,ijk->ik", bary, at.uv[at.faces[tri[hit]]])
        W, H = at.size
        col = np.clip((uv[:, 0] * W).astype(int), 0, W - 1)
        row = np.clip((uv[:, 1] * H).astype(int), 0, H - 1)
        out[hit] = result.temperature_k[row, col]
    return out.reshape(h, w)


def texture_json(result, unit: str, *, mesh_source: str = "", survey_source: str = "", extra: dict | None = None) -> str:
    """``texture.json``: counts, index → image name, unit, offsets and what was done to the values.

    ``unit``: ``K``, ``C`` or ``counts`` (raw sensor counts: the values, offsets and levelling RMS are counts)."""
    counts = unit == "counts"
    s = result.summary()
    cfg = result.config
    offsets = {name: float(o) for name, o in zip(result.view_names, result.offsets_k)}
    d = {
        "format": "thermogrammetry/texture",
        "version": 1,
        "faces_total": s["faces_total"],
        "faces_textured": s["faces_textured"],
        "faces_fully_textured": s["faces_fully_textured"],
        "faces_seen": s["faces_seen"],
        **{k: s[k] for k in ("faces_visible", "faces_visible_textured", "faces_textured_at_min_clean_radius") if k in s},
        "faces_untextured": s["faces_untextured"],
        "texels_total": s["texels_total"],
        "texels_textured": s["texels_textured"],
        "views_per_face_histogram": s["views_per_face_histogram"],
        "index": {str(i): n for i, n in enumerate(result.view_names)},
        "texels_per_image": {n: int(c) for n, c in zip(result.view_names, np.bincount(
            result.source[result.source >= 0], minlength=len(result.view_names)))},
        "occluded_texels_per_image": {n: int(c) for n, c in zip(result.view_names, result.occluded_texels)},
        "unit": unit,
        "quantity": "raw_counts" if counts else "temperature",
        "levelling": cfg.levelling.value,
        "offsets": offsets if cfg.levelling.value == "offsets" else None,
        "offsets_fixed_image": None if result.levelling_fixed is None else result.view_names[result.levelling_fixed],
        ("offsets_rms_before_after_counts" if counts else "offsets_rms_before_after_k"):
            None if result.levelling_rms_k is None else list(result.levelling_rms_k),
        "values_altered": bool(cfg.levelling.value == "offsets" or cfg.correct),
        "values_note": (("raw sensor counts (not temperatures: no documented conversion)" if counts else "temperatures")
                        + " as sampled (bilinear) from one image per texel; nothing blended or filled"
                        + ("; per-image offsets ADDED (levelling=offsets)" if cfg.levelling.value == "offsets" else "")
                        + ("; per-texel angle/emissivity/transmission correction applied" if cfg.correct else "")),
        "correction": None if not cfg.correct else {k: (v.value if hasattr(v, "value") else v)
                                                    for k, v in cfg.correction.__dict__.items()},
        "texel_size_m": s["texel_size_m"],
        "texture_size": s["texture_size"],
        "score": "f cos(theta) / d * min(1, b / b0), b0 = %.3g * min(W, H)" % cfg.border_fraction,
        "files": {"temperature": "temperature_texture.tif", "temperature_uint16": "temperature_texture_u16.tif",
                  "source": "source_texture.tif", "angle": "angle_texture.tif", "preview": "textured.png",
                  "glb": "textured.glb", "obj": "textured.obj", "vertices": "vertices.ply"},
        "mesh": mesh_source,
        "survey": survey_source,
    }
    if extra:
        d.update(extra)
    _ = from_kelvin
    return json.dumps(d, indent=1) + "\n"


_VIEWER = r"""<!doctype html><html><head><meta charset="utf-8"><title>thermogrammetry texture viewer</title>
<style>html,body{margin:0;height:100%;background:#00ff00}canvas{display:block;width:100%;height:100%}</style></head>
<body><canvas id="c"></canvas><img id="tex" src="data:image/png;base64,__PNG__" style="display:none">
<script>
// Minimal WebGL viewer of a GLB (one mesh, POSITION + TEXCOORD_0 + indices, base-colour texture), no libraries.
// y is up (glTF); the camera looks at the bounding-box centre from the south-east, above.
const GLB = "__GLB__";
function b64(s){const b=atob(s);const u=new Uint8Array(b.length);for(let i=0;i<b.length;i++)u[i]=b.charCodeAt(i);return u.buffer;}
function parseGLB(buf){
  const dv=new DataView(buf); if(dv.getUint32(0,true)!==0x46546C67) throw "not a GLB";
  let off=12, json=null, bin=null;
  while(off<buf.byteLength){const len=dv.getUint32(off,true), type=dv.getUint32(off+4,true);
    if(type===0x4E4F534A) json=JSON.parse(new TextDecoder().decode(new Uint8Array(buf,off+8,len)));
    else if(type===0x004E4942) bin=buf.slice(off+8,off+8+len);
    off+=8+len;}
  const T={5126:Float32Array,5125:Uint32Array,5123:Uint16Array,5121:Uint8Array};
  const N={SCALAR:1,VEC2:2,VEC3:3,VEC4:4};
  function acc(i){const a=json.accessors[i], v=json.bufferViews[a.bufferView];
    return new T[a.componentType](bin,(v.byteOffset||0)+(a.byteOffset||0),a.count*N[a.type]);}
  const p=json.meshes[0].primitives[0];
  return {pos:acc(p.attributes.POSITION), uv:acc(p.attributes.TEXCOORD_0), idx:acc(p.indices)};
}
function sub(a,b){return [a[0]-b[0],a[1]-b[1],a[2]-b[2]];}
function cross(a,b){return [a[1]*b[2]-a[2]*b[1],a[2]*b[0]-a[0]*b[2],a[0]*b[1]-a[1]*b[0]];}
function norm(a){const l=Math.hypot(a[0],a[1],a[2]);return [a[0]/l,a[1]/l,a[2]/l];}
function dot(a,b){return a[0]*b[0]+a[1]*b[1]+a[2]*b[2];}
function lookAt(e,c,u){const z=norm(sub(e,c)),x=norm(cross(u,z)),y=cross(z,x);
  return [x[0],y[0],z[0],0, x[1],y[1],z[1],0, x[2],y[2],z[2],0, -dot(x,e),-dot(y,e),-dot(z,e),1];}
function persp(f,a,n,fa){const t=1/Math.tan(f/2);return [t/a,0,0,0, 0,t,0,0, 0,0,(fa+n)/(n-fa),-1, 0,0,2*fa*n/(n-fa),0];}
function mul(a,b){const r=new Array(16).fill(0);for(let i=0;i<4;i++)for(let j=0;j<4;j++)for(let k=0;k<4;k++)r[j*4+i]+=a[k*4+i]*b[j*4+k];return r;}
window.onload=function(){
  const m=parseGLB(b64(GLB)), cv=document.getElementById("c");
  cv.width=cv.clientWidth; cv.height=cv.clientHeight;
  const gl=cv.getContext("webgl",{preserveDrawingBuffer:true}); if(!gl){document.title="no webgl";return;}
  gl.getExtension("OES_element_index_uint");
  const vs="attribute vec3 p;attribute vec2 t;uniform mat4 M;varying vec2 v;void main(){v=t;gl_Position=M*vec4(p,1.0);}";
  const fs="precision mediump float;uniform sampler2D s;varying vec2 v;void main(){gl_FragColor=texture2D(s,v);}";
  function sh(t,src){const o=gl.createShader(t);gl.shaderSource(o,src);gl.compileShader(o);return o;}
  const pr=gl.createProgram();gl.attachShader(pr,sh(gl.VERTEX_SHADER,vs));gl.attachShader(pr,sh(gl.FRAGMENT_SHADER,fs));gl.linkProgram(pr);gl.useProgram(pr);
  function buf(data,loc,n){const b=gl.createBuffer();gl.bindBuffer(gl.ARRAY_BUFFER,b);gl.bufferData(gl.ARRAY_BUFFER,data,gl.STATIC_DRAW);
    const l=gl.getAttribLocation(pr,loc);gl.enableVertexAttribArray(l);gl.vertexAttribPointer(l,n,gl.FLOAT,false,0,0);}
  buf(m.pos,"p",3); buf(m.uv,"t",2);
  const ib=gl.createBuffer();gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER,ib);gl.bufferData(gl.ELEMENT_ARRAY_BUFFER,new Uint32Array(m.idx),gl.STATIC_DRAW);
  const tx=gl.createTexture();gl.bindTexture(gl.TEXTURE_2D,tx);
  gl.texImage2D(gl.TEXTURE_2D,0,gl.RGB,gl.RGB,gl.UNSIGNED_BYTE,document.getElementById("tex"));
  gl.texParameteri(gl.TEXTURE_2D,gl.TEXTURE_MIN_FILTER,gl.LINEAR);gl.texParameteri(gl.TEXTURE_2D,gl.TEXTURE_MAG_FILTER,gl.LINEAR);
  gl.texParameteri(gl.TEXTURE_2D,gl.TEXTURE_WRAP_S,gl.CLAMP_TO_EDGE);gl.texParameteri(gl.TEXTURE_2D,gl.TEXTURE_WRAP_T,gl.CLAMP_TO_EDGE);
  let lo=[1e30,1e30,1e30],hi=[-1e30,-1e30,-1e30];
  for(let i=0;i<m.pos.length;i+=3)for(let k=0;k<3;k++){lo[k]=Math.min(lo[k],m.pos[i+k]);hi[k]=Math.max(hi[k],m.pos[i+k]);}
  const c=[(lo[0]+hi[0])/2,(lo[1]+hi[1])/2,(lo[2]+hi[2])/2], r=Math.hypot(hi[0]-lo[0],hi[1]-lo[1],hi[2]-lo[2])/2;
  const dir=norm(__DIR__), e=[c[0]+dir[0]*r*1.9,c[1]+dir[1]*r*1.9,c[2]+dir[2]*r*1.9];
  const M=mul(persp(0.9,cv.width/cv.height,r*0.05,r*10),lookAt(e,c,[0,1,0]));
  gl.uniformMatrix4fv(gl.getUniformLocation(pr,"M"),false,new Float32Array(M));
  gl.viewport(0,0,cv.width,cv.height);gl.clearColor(0,1,0,1);gl.enable(gl.DEPTH_TEST);
  gl.clear(gl.COLOR_BUFFER_BIT|gl.DEPTH_BUFFER_BIT);
  gl.drawElements(gl.TRIANGLES,m.idx.length,gl.UNSIGNED_INT,0);
  document.title="drawn "+(m.idx.length/3)+" triangles";
};
</script></body></html>
"""


def viewer_html(glb: bytes, *, view_direction=(0.35, -1.0, 0.55)) -> str:
    """A self-contained HTML page (plain WebGL, no libraries, works offline) showing a GLB written by
    :func:`glb_bytes`: the GLB and its texture are embedded as base64, background pure green (0, 255, 0).
    ``view_direction``: from the model's centre towards the eye, in the survey frame (x east, y north, z up;
    mapped to the GLB's Y-up axes)."""
    import base64
    import struct

    data = bytes(glb)
    # the texture: first image of the GLB, for an <img> that the page loads before 'load' fires
    jlen = struct.unpack_from("<I", data, 12)[0]
    js = json.loads(data[20:20 + jlen])
    bin_off = 20 + jlen + 8
    img = js["images"][0]
    bv = js["bufferViews"][img["bufferView"]]
    png = data[bin_off + bv.get("byteOffset", 0): bin_off + bv.get("byteOffset", 0) + bv["byteLength"]]
    dx, dy, dz = (float(x) for x in view_direction)
    d = ",".join(f"{x:.6g}" for x in (dx, dz, -dy))
    return (_VIEWER.replace("__GLB__", base64.b64encode(data).decode()).replace("__PNG__", base64.b64encode(png).decode())
            .replace("__DIR__", f"[{d}]"))
