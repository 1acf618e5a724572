"""The table of every learned backend's weights: where they come from, what they weigh, which param takes them."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class WeightsFile:
    """One file of an entry: a path inside a Hugging Face repo, or a file downloaded from an official URL."""

    path: str
    """Path inside the repo (hub entries), or the file name it is saved under (URL entries)."""
    url: str | None = None
    """Official download URL for files not on the hub; None for hub files."""
    size: int | None = None
    """Exact size in bytes, where published; checked after download."""
    sha256: str | None = None
    """Full sha256 hex, or a published prefix of it (>= 8 hex digits, e.g. torchvision's file-name hashes)."""


@dataclass(frozen=True)
class Use:
    """One place the weights go: a pipeline param (`STAGE.PARAM`) or a flag of another verb (`eval --lpips-weights`)."""

    param: str
    """`depth.depth_anything.weights` (set with `--set` / scene.yaml) or `VERB --flag` (a flag of `python runner.py VERB`)."""
    file: str | None = None
    """Which file of the entry it takes; None = the entry's directory (hub entries) or its only file."""
    also: tuple[str, ...] = ()
    """Other settings the backend needs: `STAGE.PARAM=VALUE` (e.g. `depth.backend=depth-anything`) for a param use,
    `--flag value` for a flag use."""


@dataclass(frozen=True)
class WeightsEntry:
    name: str
    """Registry name used by `python runner.py weights fetch NAME`."""
    model: str
    """What the weights are, in words."""
    licence: str
    size: str
    """Approximate download size, in words (e.g. '99 MB')."""
    uses: tuple[Use, ...]
    repo: str | None = None
    """Hugging Face model id (ORG/NAME) for hub entries."""
    revision: str = "main"
    files: tuple[WeightsFile, ...] = ()
    """Hub entries: the files a backend needs (checked for presence; allow_patterns of the download when
    `patterns` is empty); URL entries: every file to download."""
    patterns: tuple[str, ...] = ()
    """Hub entries: allow_patterns of the snapshot download (default: the whole repo)."""
    trained: str | None = None
    """Set for weights this project trains instead of fetching: the command that produces them."""
    notes: str = ""

    @property
    def kind(self) -> str:
        return "trained" if self.trained else "hf" if self.repo else "url"

    @property
    def source(self) -> str:
        if self.trained:
            return f"trained: {self.trained}"
        if self.repo:
            return f"hf:{self.repo}" + (f"@{self.revision}" if self.revision != "main" else "")
        return ", ".join(f.url or f.path for f in self.files)


REGISTRY: dict[str, WeightsEntry] = {}


def register(entry: WeightsEntry) -> WeightsEntry:
    """Add an entry to the table (other modules append their own feature networks); duplicate names are an error."""
    if entry.name in REGISTRY and REGISTRY[entry.name] != entry:
        raise ValueError(f"weights registry: {entry.name!r} is already registered")
    REGISTRY[entry.name] = entry
    return entry


def find_by_repo(repo: str) -> WeightsEntry | None:
    """The registry entry of a Hugging Face repo id, if any (case-insensitive, as the hub is)."""
    return next((e for e in REGISTRY.values() if e.repo and e.repo.lower() == repo.lower()), None)


_DA_FILES = (WeightsFile("config.json"), WeightsFile("model.safetensors"), WeightsFile("preprocessor_config.json"))
_DA_USE = Use("depth.depth_anything.weights", also=("depth.backend=depth-anything",))
for _size, _mb, _lic in (("small", "99 MB (24.8M params, fp32)", "Apache-2.0"),
                         ("base", "390 MB (97.5M params, fp32)", "CC-BY-NC-4.0 (non-commercial)"),
                         ("large", "1.3 GB (335M params, fp32)", "CC-BY-NC-4.0 (non-commercial)")):
    register(WeightsEntry(
        name=f"depth-anything-v2-{_size}", model=f"Depth Anything V2 {_size.capitalize()} (relative depth, transformers)",
        repo=f"depth-anything/Depth-Anything-V2-{_size.capitalize()}-hf", licence=_lic, size=_mb, files=_DA_FILES,
        uses=(_DA_USE,),
        notes="depth for RGB-only panoramas (6 cube views merged)" + ("" if _size == "small" else "; check the licence"),
    ))

register(WeightsEntry(
    name="wan2.2-ti2v-5b", model="Wan2.2-TI2V-5B base video model (diffusers layout)",
    repo="Wan-AI/Wan2.2-TI2V-5B-Diffusers", licence="Apache-2.0", size="about 30 GB (transformer, UMT5-XXL text encoder, VAE)",
    files=(WeightsFile("model_index.json"), WeightsFile("transformer/config.json"), WeightsFile("vae/config.json"),
           WeightsFile("text_encoder/config.json"), WeightsFile("tokenizer/tokenizer_config.json")),
    patterns=("model_index.json", "transformer/*", "vae/*", "text_encoder/*", "tokenizer/*", "scheduler/*"),
    uses=(Use("video.wan.weights", also=("video.backend=wan-shortcut",)),),
    notes="the base model only: the LoRA and extra weights (video.wan.lora, video.wan.extra_weights) are trained by this "
          "project, see wan-shortcut-lora",
))

register(WeightsEntry(
    name="realesrgan-x2plus", model="Real-ESRGAN x2plus (RRDBNet, x2 upscaling)", licence="BSD-3-Clause", size="64 MB",
    files=(WeightsFile("RealESRGAN_x2plus.pth",
                       url="https://github.com/xinntao/Real-ESRGAN/releases/download/v0.2.1/RealESRGAN_x2plus.pth"),),
    uses=(Use("video.upscale_weights", also=("video.upscale=realesrgan",)),),
    notes="official Real-ESRGAN GitHub release v0.2.1",
))

_LPIPS_LIN = "https://github.com/richzhang/PerceptualSimilarity/raw/master/lpips/weights/v0.1/{}.pth"
register(WeightsEntry(
    name="lpips-alex", model="LPIPS v0.1 with an AlexNet backbone (torchvision ImageNet weights + linear heads)",
    licence="BSD-3-Clause (torchvision), BSD-2-Clause (lpips)", size="233 MB",
    files=(WeightsFile("alexnet-owt-7be5be79.pth", url="https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
                       sha256="7be5be79"),
           WeightsFile("alex.pth", url=_LPIPS_LIN.format("alex"))),
    uses=(Use("eval --lpips-weights", file="alexnet-owt-7be5be79.pth"), Use("eval --lpips-lin-weights", file="alex.pth")),
    notes="torchvision's file names carry the first 8 hex digits of their sha256, checked after download",
))
register(WeightsEntry(
    name="lpips-vgg", model="LPIPS v0.1 with a VGG16 backbone (torchvision ImageNet weights + linear heads)",
    licence="BSD-3-Clause (torchvision), BSD-2-Clause (lpips)", size="528 MB",
    files=(WeightsFile("vgg16-397923af.pth", url="https://download.pytorch.org/models/vgg16-397923af.pth", sha256="397923af"),
           WeightsFile("vgg.pth", url=_LPIPS_LIN.format("vgg"))),
    uses=(Use("eval --lpips-weights", file="vgg16-397923af.pth", also=("--lpips-net vgg",)),
          Use("eval --lpips-lin-weights", file="vgg.pth")),
))
register(WeightsEntry(
    name="fid-inception", model="InceptionV3 of FID (TF 2015-12-05 graph ported by pytorch-fid)",
    licence="Apache-2.0", size="about 90 MB",
    files=(WeightsFile("pt_inception-2015-12-05-6726825d.pth",
                       url="https://github.com/mseitzer/pytorch-fid/releases/download/fid_weights/"
                           "pt_inception-2015-12-05-6726825d.pth"),),
    uses=(Use("eval --fid-weights"),),
    notes="FID of `eval DATASET --all` (panoworld/models/inception.py defines the network in torch)",
))
register(WeightsEntry(
    name="fvd-i3d", model="I3D (Kinetics-400) of FVD as TorchScript, as exported by StyleGAN-V",
    licence="Apache-2.0 (DeepMind kinetics-i3d)", size="tens of MB",
    files=(WeightsFile("i3d_torchscript.pt", url="https://www.dropbox.com/s/ge9e5ujwgetktms/i3d_torchscript.pt?dl=1"),),
    uses=(Use("eval --fvd-weights"),),
    notes="FVD of `eval DATASET --all` (panoworld/models/i3d.py loads it with torch.jit)",
))

register(WeightsEntry(
    name="wan-shortcut-lora", model="PanoWorld shortcut LoRA + widened patch/step-size embeddings for Wan2.2-TI2V-5B",
    licence="this project's", size="about 0.5 GB", trained="python runner.py train video",
    uses=(Use("video.wan.lora"), Use("video.wan.extra_weights")),
    notes="no public release: trained by this project on precomputed conditions",
))
register(WeightsEntry(
    name="rig-unet", model="small U-Net segmenting the capture rig on the downward cube face (the learned rig detector)",
    licence="this project's", size="about 0.5 MB (0.12M params, fp32)",
    trained="python bench/bench_rig_learned.py --quick --out DIR",
    uses=(Use("depth.rig_weights", also=("depth.rig_detector=learned",)),),
    notes="trained by this project on synthetic tripods (runner.py synth --rig); no public rig segmenter exists",
))
register(WeightsEntry(
    name="panovggt", model="panoramic VGGT (feed-forward poses and depth)", licence="this project's", size="-",
    trained="python runner.py train recon", uses=(Use("poses.vggt.weights", also=("poses.backend=vggt",)),),
    notes="no public panoramic VGGT checkpoint exists; trained by this project",
))
register(WeightsEntry(
    name="gs-decoder", model="voxel-aligned Gaussian decoder", licence="this project's", size="-",
    trained="python runner.py train recon", uses=(Use("gaussians.decoder.weights", also=("gaussians.backend=decoder",)),),
    notes="trained by this project together with panovggt",
))
