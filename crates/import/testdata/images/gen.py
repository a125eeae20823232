import zlib, struct
W, H = 24, 16
def px(x, y):
    return ((x * 255) // (W - 1), (y * 255) // (H - 1), 255 - (x * 5 + y * 6), 255 - y * 8)
def png(name, f, alpha):
    raw = b''
    for y in range(H):
        raw += b'\0'
        for x in range(W):
            p = f(x, y)
            raw += bytes(p if alpha else p[:3])
    def chunk(t, d):
        return struct.pack('>I', len(d)) + t + d + struct.pack('>I', zlib.crc32(t + d) & 0xffffffff)
    ihdr = struct.pack('>IIBBBBB', W, H, 8, 6 if alpha else 2, 0, 0, 0)
    open(name, 'wb').write(b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', ihdr) + chunk(b'IDAT', zlib.compress(raw)) + chunk(b'IEND', b''))
png('opaque.png', px, False)
png('alpha.png', px, True)
png('inverted.png', lambda x, y: tuple(255 - c for c in px(x, y)[:3]) + (255,), True)
