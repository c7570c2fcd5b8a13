// Builds the single page into services/api/static/, which the API serves at / (services/api/web.py).
// build-info.json records a hash of the sources, so a Python test can tell a stale committed build.
import { createHash } from "node:crypto";
import { readdirSync, readFileSync, statSync } from "node:fs";
import { join, relative, sep } from "node:path";
import { fileURLToPath } from "node:url";
import { defineConfig, type Plugin } from "vite";

const root = fileURLToPath(new URL(".", import.meta.url));
const SOURCE_FILES = ["index.html", "package.json", "package-lock.json", "tsconfig.json", "vite.config.ts"];

function walk(dir: string): string[] {
  return readdirSync(dir).flatMap((name) => {
    const path = join(dir, name);
    return statSync(path).isDirectory() ? walk(path) : [path];
  });
}

/** sha256 over "relative/path\nsha256(content)\n" of every source file, in sorted path order. */
export function sourcesHash(): { sha256: string; files: number } {
  const files = [...SOURCE_FILES.map((f) => join(root, f)), ...walk(join(root, "src"))]
    .map((path) => relative(root, path).split(sep).join("/"))
    .sort();
  const hash = createHash("sha256");
  for (const file of files) {
    const content = createHash("sha256").update(readFileSync(join(root, file))).digest("hex");
    hash.update(`${file}\n${content}\n`);
  }
  return { sha256: hash.digest("hex"), files: files.length };
}

function buildInfo(): Plugin {
  return {
    name: "spine-build-info",
    generateBundle() {
      const { sha256, files } = sourcesHash();
      this.emitFile({
        type: "asset",
        fileName: "build-info.json",
        source: JSON.stringify({ sources_sha256: sha256, source_files: files }, null, 2) + "\n",
      });
    },
  };
}

export default defineConfig({
  root,
  base: "/",
  plugins: [buildInfo()],
  build: {
    outDir: "../services/api/static",
    emptyOutDir: true,
    assetsDir: "assets",
    target: "es2022",
    sourcemap: false,
    chunkSizeWarningLimit: 1024,
  },
});
