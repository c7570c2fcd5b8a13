// Builds the single page into services/api/static/, which the API serves at / (services/api/web.py).
// build-info.json records a hash of the sources, so a Python test can tell a stale committed build.
import { createHash } from "node:crypto";
import { copyFileSync, mkdirSync, readdirSync, readFileSync, statSync, writeFileSync } from "node:fs";
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

/**
 * The API documentation pages' assets, served by the service itself (services/api/docs_ui.py),
 * copied from the pinned npm packages with their licences: Swagger UI (swagger-ui-dist,
 * Apache-2.0) and ReDoc (redoc's standalone bundle, MIT). No CDN.
 */
const DOCS_ASSETS: [string, string][] = [
  ["swagger-ui-dist/swagger-ui-bundle.js", "swagger-ui-bundle.js"],
  ["swagger-ui-dist/swagger-ui.css", "swagger-ui.css"],
  ["swagger-ui-dist/LICENSE", "swagger-ui.LICENSE.txt"],
  ["swagger-ui-dist/NOTICE", "swagger-ui.NOTICE.txt"],
  ["redoc/bundles/redoc.standalone.js", "redoc.standalone.js"],
  ["redoc/LICENSE", "redoc.LICENSE.txt"],
];
const SWAGGER_INIT = `// Starts Swagger UI on this service's /openapi.json (a file, so the page needs no inline script).
window.ui = SwaggerUIBundle({ url: "/openapi.json", dom_id: "#swagger-ui", deepLinking: true });
`;

function docsAssets(): Plugin {
  return {
    name: "spine-docs-assets",
    writeBundle(options) {
      const out = join(options.dir ?? join(root, "../services/api/static"), "docs");
      mkdirSync(out, { recursive: true });
      for (const [from, to] of DOCS_ASSETS) copyFileSync(join(root, "node_modules", from), join(out, to));
      writeFileSync(join(out, "swagger-init.js"), SWAGGER_INIT);
      const versions = Object.fromEntries(["swagger-ui-dist", "redoc"].map((p) => [p, JSON.parse(readFileSync(join(root, "node_modules", p, "package.json"), "utf8")).version]));
      writeFileSync(join(out, "versions.json"), JSON.stringify(versions, null, 2) + "\n");
    },
  };
}

export default defineConfig({
  root,
  base: "/",
  plugins: [buildInfo(), docsAssets()],
  build: {
    outDir: "../services/api/static",
    emptyOutDir: true,
    assetsDir: "assets",
    target: "es2022",
    sourcemap: false,
    chunkSizeWarningLimit: 1024,
  },
});
