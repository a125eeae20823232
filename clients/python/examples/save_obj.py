#!/usr/bin/env python3
"""Saves one posed head of a running crowdmorph server as a Wavefront OBJ file.

    python3 save_obj.py --url http://127.0.0.1:8080 --rig default-head --clip talk --frame 12 \\
        --out head.obj

The topology (triangles) and texture coordinates come from ``GET /v1/rigs/{id}/mesh?lod=L``
once; the posed vertices and normals from ``POST /v1/crowd/frame`` for a crowd of one head, in
the format asked for (``f32`` is exact; ``f16`` and ``q16`` are decoded to float). When the rig
has materials, they go in an MTL file beside the OBJ and its textures in files beside that
(``GET /v1/rigs/{id}/materials`` and ``/textures/{i}``). Open the file in any 3D viewer.
"""

import argparse
import os
import sys

import crowdmorph


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--url", default="http://127.0.0.1:8080", help="server URL")
    p.add_argument("--token", default=None, help="admin token (not needed to read)")
    p.add_argument("--rig", default="default-head", help="rig id")
    p.add_argument("--clip", default="talk", help="clip name")
    p.add_argument("--frame", type=int, default=12, help="frame (wraps past the end)")
    p.add_argument("--lod", type=int, default=0, help="level of detail")
    p.add_argument("--format", default="f32", choices=["f32", "f16", "q16"])
    p.add_argument("--out", default="head.obj", help="OBJ file to write")
    args = p.parse_args(argv)

    with crowdmorph.Client(args.url, token=args.token) as client:
        try:
            mesh = client.mesh(args.rig, lod=args.lod)
            frame = client.crowd_frame(
                [crowdmorph.Head(0, args.rig, args.clip, args.frame, args.lod)],
                format=args.format,
                normals=True,
            )
            looks = client.materials(args.rig)
            stem = os.path.splitext(args.out)[0]
            folder = os.path.dirname(args.out)
            # Each image in a file beside the OBJ, named after it.
            image_files = []
            for i, image in enumerate(looks["images"]):
                data, content_type = client.texture_at(image["uri"])
                ext = {"image/png": "png", "image/jpeg": "jpg", "image/webp": "webp"}.get(
                    content_type, "bin"
                )
                name = f"{os.path.basename(stem)}_{i}.{ext}"
                with open(os.path.join(folder, name), "wb") as f:
                    f.write(data)
                image_files.append(name)
        except crowdmorph.CrowdmorphError as e:
            print(f"error: {e.code}: {e.message}", file=sys.stderr)
            return 1
    head = frame.buffer(0)
    mtllib = None
    names = []
    if looks["materials"]:
        mtllib = os.path.basename(stem) + ".mtl"
        names = crowdmorph.write_mtl(stem + ".mtl", looks, image_files)
    groups = [
        (p.name.replace(" ", "_"), p.first_index, p.indices, names[p.material] if p.material is not None and p.material < len(names) else None)
        for p in mesh.primitives
    ]
    verts, tris = crowdmorph.write_obj(
        args.out,
        head.positions,
        mesh.indices,
        head.normals,
        comment=(
            f"crowdmorph {args.rig} clip {head.clip} frame {head.frame} lod {head.lod} "
            f"({frame.format}) from {args.url}"
        ),
        uvs=mesh.uvs,
        groups=groups,
        mtllib=mtllib,
    )
    extra = f", {mtllib} and {len(image_files)} images" if mtllib else ""
    print(f"wrote {args.out}: {verts} vertices, {tris} triangles{extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
